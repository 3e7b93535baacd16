"""Speech that is not a command: espeak-ng speech and garbage audio through the real pocketsphinx decoder.

The JSGF decoder forces these utterances onto grammar phrases (measured: "please pass me the salt"
→ "reset the robot", "robot please excuse me" → "robot please execute"); the recognizer's acoustic
score rule must reject them, say why, and never let one confirm a staged critical command.
"""

from __future__ import annotations

import io
import json
import shutil
import wave

import numpy as np
import pytest

from telerig.errors import DeviceError
from telerig.voice.dispatch import Dispatcher
from telerig.voice.feedback import synthesize
from telerig.voice.grammar import CONFIRMATION, parse
from telerig.voice.node import listen
from telerig.voice.recognizer import MAX_AUDIO_S, Heard, Recognizer, read_wav


@pytest.fixture(scope="module")
def recognizer() -> Recognizer:
    assert shutil.which("espeak-ng"), (
        "espeak-ng is missing: apt-get install espeak-ng (scripts/system-deps.sh)"
    )
    return Recognizer()  # raises DependencyError naming `pip install 'telerig[voice]'`


def _wav(samples: np.ndarray, rate: int = 16_000) -> bytes:
    buf = io.BytesIO()
    with wave.open(buf, "wb") as w:
        w.setnchannels(1)
        w.setsampwidth(2)
        w.setframerate(rate)
        w.writeframes(np.asarray(samples).clip(-32768, 32767).astype("<i2").tobytes())
    return buf.getvalue()


def _pcm(wav: bytes) -> np.ndarray:
    return read_wav(wav)


@pytest.mark.parametrize(
    "said",
    [
        # Each of these came out of the grammar-only decoder as a full command phrase.
        "please pass me the salt",  # → reset the robot (critical)
        "what is the weather today",  # → automatic view
        "turn left at the next corner",  # → start episode
        "thank you very much",  # → execute the plan (critical)
    ],
)
def test_everyday_speech_is_rejected_with_a_reason(recognizer: Recognizer, said: str) -> None:
    heard = recognizer.recognize_wav(synthesize(said))
    assert not heard.command, heard
    assert heard.reason, heard
    assert heard.reason.startswith("not a command"), heard.reason
    assert "\n" not in heard.reason


def test_in_grammar_phrases_are_still_accepted(recognizer: Recognizer) -> None:
    for phrase in ("manipulation", "stop the robot", CONFIRMATION):
        heard = recognizer.recognize_wav(synthesize(phrase))
        assert heard.command, heard
        assert heard.text == phrase, heard


def test_near_misses_of_the_confirmation_never_confirm(recognizer: Recognizer) -> None:
    sent: list[tuple[str, bytes]] = []
    dispatcher = Dispatcher("demo", lambda t, p, q, r: sent.append((t, p)))
    near = ["robot please excuse me", "robot execute", "robot please wait"]
    replies = []
    for phrase in near:
        staged = dispatcher.handle("release emergency stop", source="cli")
        assert staged.status == "staged"
        replies += listen(dispatcher, recognizer, [synthesize(phrase)])
    assert [r.status for r in replies] == ["rejected"] * len(near), replies
    assert all(r.say.startswith("not a command") for r in replies), replies
    assert not [t for t, _ in sent if t.endswith("/safety/command")]
    # Said back on the feedback topic, like a rejected typed phrase.
    said_back = [json.loads(p) for t, p in sent if t.endswith("/voice/feedback")]
    assert [d["status"] for d in said_back].count("rejected") == len(near)


def test_garbage_audio_is_rejected_or_a_one_line_error(recognizer: Recognizer) -> None:
    rng = np.random.default_rng(7)
    speech = _pcm(synthesize("navigation"))
    cases: dict[str, bytes] = {
        "white noise": _wav(rng.normal(0, 8000, 16_000)),
        "hum": _wav(20_000 * np.sin(2 * np.pi * 50 * np.arange(16_000) / 16_000)),
        "clicks": _wav(np.where(np.arange(16_000) % 1600 < 8, 30_000, 0)),
        "10 ms": _wav(rng.normal(0, 8000, 160)),
        "full-scale square": _wav(np.sign(np.sin(np.arange(32_000) / 7.0)) * 32_767),
        f"{MAX_AUDIO_S - 1:.0f} s of noise": _wav(rng.normal(0, 300, int((MAX_AUDIO_S - 1) * 16_000))),
    }
    for what, wav in cases.items():
        heard = recognizer.recognize_wav(wav)
        assert not heard.command, (what, heard)
        assert heard.silent or (heard.reason and "\n" not in heard.reason), (what, heard)
    # Clipped speech: heard as what was said, or rejected; never as another command.
    clipped = recognizer.recognize_wav(_wav(np.clip(speech * 40, -32_000, 32_000)))
    assert not clipped.command or clipped.text == "navigation", clipped
    for bad, says in ((b"", "not a WAV"), (_wav(np.zeros(0)), "no audio")):
        with pytest.raises(DeviceError, match=says):
            recognizer.recognize_wav(bad)


def test_silence_is_silent_not_rejected(recognizer: Recognizer) -> None:
    heard = recognizer.recognize_wav(_wav(np.zeros(8000)))
    assert heard == Heard("", False)
    assert heard.silent
    assert parse(heard.text).command is None
