"""Offline speech recognition of the command grammar: pocketsphinx 5 with a JSGF grammar of its phrases.

The decoder only ever hears the grammar's phrases (its JSGF is generated from
:data:`~telerig.voice.grammar.COMMANDS`), so a hypothesis is either a phrase or a partial path the
grammar parser rejects; whether the audio really was that phrase is decided by its acoustic
score (below). The wheel ships the US-English acoustic model and dictionary: nothing is downloaded.

Audio is 16-bit PCM; it is mixed to mono, resampled to the model's 16 kHz, peak-normalized and
padded with silence before decoding. Why normalize: with espeak-ng speech at its default level
(peaks ~20 000 of 32 767) 26 of 31 grammar phrases were recognized, and 31 of 31 at speaking rates
125-160 wpm once peaks were scaled to 2 000 (the decoder's noise and silence estimates work on
absolute energy). Why pad: the first 0.4 s let batch CMN and the noise estimate see silence.

Out-of-grammar speech. A JSGF decoder forces every utterance onto the grammar: "please pass me the
salt" comes out as "reset the robot", "robot please excuse me" as "robot please execute". So a phrase
is only accepted as a command when the audio fits it, measured by the acoustic score of its words:
pocketsphinx's word score is the log-likelihood of the word's frames relative to the best of the
senones scored in each frame (a crude garbage model that fits anything), here per 10 ms frame
[nats/frame]: one pass, no extra decode.
The rule (:func:`verdict`): the mean over the phrase's words must be at least :data:`MIN_SCORE`, and
for the confirmation ``robot please execute`` every word must reach :data:`MIN_CONFIRM_WORD_SCORE`.
Measured by benchmarks/voice_recognition.py (espeak-ng at 125/140/160 wpm; before = the grammar
decoder alone): in-grammar phrasings accepted 216/228 (before 228/228; 'limit directions' and
'scale down' score low at every rate, every command keeps a phrasing that passes); out-of-grammar
utterances rejected 135/144 (before 74/144), non-speech 7/7 (before 6/7); accepted as a critical
command 0 (before 10), as the confirmation 0 (before 9). Still accepted: 'please stop talking' as
'restart episode' at all rates, and 6 near misses at 125 wpm ('start the engine' as 'start episode').
Why not a garbage model in the grammar: a 39-phone loop beside the phrases took > 5 s per utterance;
keyword spotting missed most espeak-ng phrases even at 1e-30; a second free decode with
en-us.lm.bin took 1-3 s and its scores overlapped as much.
"""

from __future__ import annotations

import io
import math
import wave
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from telerig.errors import DependencyError, DeviceError
from telerig.ir.types import FloatArray
from telerig.voice.grammar import CONFIRMATION, parse, phrases

if TYPE_CHECKING:
    from pocketsphinx import Decoder  # type: ignore[import-untyped]  # no stubs or py.typed

__all__ = [
    "MAX_AUDIO_BYTES",
    "MAX_AUDIO_S",
    "MIN_CONFIRM_WORD_SCORE",
    "MIN_SCORE",
    "SAMPLE_RATE",
    "Heard",
    "Recognizer",
    "jsgf",
    "read_wav",
    "verdict",
]

#: Sample rate of the acoustic model [Hz].
SAMPLE_RATE = 16_000
#: Longest utterance decoded [s]: a command is a few words.
MAX_AUDIO_S = 15.0
#: Largest WAV accepted [bytes] (15 s of 48 kHz stereo 16-bit is 2.9 MB).
MAX_AUDIO_BYTES = 4 << 20
#: Peak level the audio is scaled to before decoding (of 32 767; see the module docs).
_PEAK = 2000.0
#: Silence added before and after the utterance [s].
_PAD_S = 0.4
#: Below this peak the audio is silence: nothing to decode.
_SILENT_PEAK = 50.0
#: Lowest mean word score of an accepted phrase [nats/frame]. The benchmark's sweep (in-grammar
#: accepted of 228, out-of-grammar and noise rejected of 151): -5.0: 222, 124; -4.5: 217, 135;
#: -4.25: 216, 142; -4.0: 213, 145; -3.5: 199, 148. Below -4.25 rejections fall fast, above it
#: acceptances do. Lowest in-grammar: 'scale down' at 160 wpm, -7.2.
MIN_SCORE = -4.25
#: Lowest score of each word of the confirmation phrase [nats/frame]: in-grammar its worst word
#: scored -1.73 to -2.01 at 125-160 wpm, the near misses forced onto it -2.91 ('robot please excuse
#: me', the best of them), -6.06 ('robot execute': 'please' squeezed into 15 frames), -9.3 ('robot
#: please wait'). A rejected confirmation is said again; an accepted near miss would move a robot.
MIN_CONFIRM_WORD_SCORE = -2.5


def jsgf() -> str:
    """The JSGF grammar of every phrase of the command grammar."""
    body = " | ".join(f"( {p} )" for p in phrases())
    return f"#JSGF V1.0;\ngrammar telerig;\npublic <command> = {body};\n"


def _decoder_class() -> type[Decoder]:
    try:
        from pocketsphinx import Decoder
    except ImportError as exc:
        raise DependencyError(
            "pocketsphinx is missing (voice commands): pip install 'telerig[voice]'"
        ) from exc
    decoder: type[Decoder] = Decoder
    return decoder


def read_wav(source: Path | bytes) -> FloatArray:
    """A WAV file (path or bytes) as mono samples at :data:`SAMPLE_RATE` (float, PCM16 scale).

    Raises:
        DeviceError: Not a 16-bit PCM WAV, larger than :data:`MAX_AUDIO_BYTES`, longer than
            :data:`MAX_AUDIO_S` or empty; one line naming what to fix.
    """
    what = str(source) if isinstance(source, Path) else "the audio"
    try:
        data = source.read_bytes() if isinstance(source, Path) else source
    except OSError as exc:
        raise DeviceError(f"cannot read {what}: {exc.strerror or exc}") from None
    if len(data) > MAX_AUDIO_BYTES:
        raise DeviceError(
            f"{what} is {len(data) >> 10} kB, over {MAX_AUDIO_BYTES >> 20} MB: send one short command"
        )
    try:
        with wave.open(io.BytesIO(data)) as w:
            width, channels, rate, n = w.getsampwidth(), w.getnchannels(), w.getframerate(), w.getnframes()
            if width != 2:
                raise DeviceError(f"{what} has {8 * width}-bit samples: record 16-bit PCM WAV")
            if not 8000 <= rate <= 96_000:
                raise DeviceError(
                    f"{what} has a sample rate of {rate} Hz: record at 16 kHz (8-96 kHz accepted)"
                )
            # A streamed WAV (a pipe's) has no real length in its header: count what is there.
            raw = w.readframes(min(n, int(MAX_AUDIO_S * rate) + 1))
            if len(raw) // (width * channels) > MAX_AUDIO_S * rate:
                raise DeviceError(f"{what} is longer than {MAX_AUDIO_S:.0f} s: one command at a time")
    except (wave.Error, EOFError) as exc:
        raise DeviceError(f"{what} is not a WAV file ({exc}): record 16-bit PCM WAV") from None
    samples = np.frombuffer(raw[: len(raw) - len(raw) % (2 * channels)], dtype="<i2").astype(np.float64)
    if samples.size == 0:
        raise DeviceError(f"{what} holds no audio")
    mono = samples.reshape(-1, channels).mean(axis=1)
    return resample(mono, rate)


def resample(samples: FloatArray, rate: int) -> FloatArray:
    """``samples`` at ``rate`` [Hz] resampled to :data:`SAMPLE_RATE` (polyphase, anti-aliased)."""
    if rate == SAMPLE_RATE:
        return samples
    from scipy.signal import resample_poly  # type: ignore[import-untyped]  # no stubs installed

    g = math.gcd(SAMPLE_RATE, rate)
    out: FloatArray = resample_poly(samples, SAMPLE_RATE // g, rate // g)
    return out


def _prepare(samples: FloatArray) -> bytes | None:
    peak = float(np.abs(samples).max()) if samples.size else 0.0
    if not math.isfinite(peak) or peak < _SILENT_PEAK:
        return None
    pad = np.zeros(int(_PAD_S * SAMPLE_RATE))
    scaled = np.concatenate([pad, samples * (_PEAK / peak), pad])
    # A little fixed dither: digital silence has no energy to estimate noise from.
    scaled += np.random.default_rng(0).normal(0.0, 3.0, scaled.size)
    return np.clip(np.round(scaled), -32768, 32767).astype("<i2").tobytes()


@dataclass(frozen=True, slots=True)
class Heard:
    """What one utterance was.

    Attributes:
        text: The grammar phrase the decoder fitted (``""`` for silence, or when no whole phrase fit).
        command: Whether ``text`` is accepted as the command phrase said (see :func:`verdict`).
        reason: Why it is not a command (one line to say back); ``None`` when accepted or silent.
        score: Mean acoustic score of the phrase's words [nats/frame]; ``None`` without words.
        worst: Score of its worst word [nats/frame]; ``None`` without words.
    """

    text: str
    command: bool
    reason: str | None = None
    score: float | None = None
    worst: float | None = None

    @property
    def silent(self) -> bool:
        """Nothing was said (no audio above the silence level)."""
        return not self.command and self.reason is None


def verdict(text: str, words: list[tuple[float, int]]) -> Heard:
    """Accept or reject the phrase ``text`` from its words' ``(log score [nats], frames)``.

    Accepted: ``text`` is a whole grammar phrase, the mean of the words' scores per frame is at least
    :data:`MIN_SCORE` and, for :data:`~telerig.voice.grammar.CONFIRMATION`, every word's is at least
    :data:`MIN_CONFIRM_WORD_SCORE`. The numbers behind both are in the module docs.
    """
    frames = sum(n for _, n in words)
    score = sum(s for s, _ in words) / frames if frames else None
    worst = min((s / n for s, n in words if n > 0), default=None)
    if not text or parse(text).command is None or score is None or worst is None:
        return Heard(text, False, "not a command: no command phrase heard", score, worst)
    if score < MIN_SCORE:
        why = f"not a command: sounded only vaguely like '{text}' ({score:.1f} < {MIN_SCORE} nats/frame)"
        return Heard(text, False, why, score, worst)
    if text == CONFIRMATION and worst < MIN_CONFIRM_WORD_SCORE:
        why = (
            f"not a command: not clearly '{CONFIRMATION}' (a word scored {worst:.1f} < "
            f"{MIN_CONFIRM_WORD_SCORE} nats/frame), say it again"
        )
        return Heard(text, False, why, score, worst)
    return Heard(text, True, None, score, worst)


#: A word score of 0 (the probability underflowed a double: below ~-709 nats) counts as this [nats].
_UNDERFLOW = -1e4


class Recognizer:
    """Decodes one utterance at a time into the grammar phrase it most likely is, or rejects it.

    Building it loads the model (~0.5 s); :meth:`recognize` takes ~0.1-0.3 s per utterance on one
    core. Not thread-safe: one decoder per thread.

    Raises:
        DependencyError: pocketsphinx is not installed (the fix: ``pip install 'telerig[voice]'``).
    """

    def __init__(self) -> None:
        decoder_class = _decoder_class()
        self._decoder = decoder_class(lm=None, loglevel="FATAL")
        self._decoder.add_jsgf_string("commands", jsgf())
        self._decoder.activate_search("commands")
        #: Utterances decoded, those that were silence (not decoded), those rejected as no command.
        self.decoded = 0
        self.silent = 0
        self.rejected = 0

    def recognize(self, samples: FloatArray) -> Heard:
        """What ``samples`` (mono, :data:`SAMPLE_RATE`, PCM16 scale) say: a command phrase, speech that
        is not a command (with the reason to say back), or silence (see :class:`Heard`)."""
        audio = _prepare(np.asarray(samples, dtype=np.float64))
        if audio is None:
            self.silent += 1
            return Heard("", False)
        d = self._decoder
        d.start_utt()
        try:
            d.process_raw(audio, full_utt=True)
        finally:
            d.end_utt()  # an interrupted utterance must not block the next one
        self.decoded += 1
        hyp = d.hyp()
        text = "" if hyp is None else str(hyp.hypstr)
        words = []
        for seg in d.seg() or ():
            if str(seg.word).startswith(("<", "[", "+")):  # silence and noise fillers
                continue
            # ascore is exp(log score): the Python API hands it back in the probability domain.
            p = float(seg.ascore)
            words.append((math.log(p) if p > 0 else _UNDERFLOW, int(seg.end_frame - seg.start_frame + 1)))
        heard = verdict(text, words)
        self.rejected += not heard.command
        return heard

    def recognize_wav(self, source: Path | bytes) -> Heard:
        """:meth:`recognize` of a WAV file (see :func:`read_wav` for what it accepts)."""
        return self.recognize(read_wav(source))
