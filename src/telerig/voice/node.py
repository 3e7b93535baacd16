"""The voice node: audio (WAV files or a microphone through ``arecord``) or text → dispatcher → bus."""

from __future__ import annotations

import logging
import shutil
import subprocess
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from telerig.bus.base import Bus
from telerig.bus.topics import Topic
from telerig.errors import DependencyError, DeviceError
from telerig.voice.dispatch import AID_STREAMS, Dispatcher, Reply
from telerig.voice.recognizer import SAMPLE_RATE, Recognizer

__all__ = ["connect_dispatcher", "listen", "microphone", "say_text"]

log = logging.getLogger(__name__)

#: How long a new client waits for the robots' retained aid states before acting [s] (they arrive
#: right after the subscription; a broker on the LAN answers in a few ms).
_SETTLE_S = 0.3


def connect_dispatcher(
    bus: Bus,
    rig: str,
    *,
    robot: str | None = None,
    source: str = "voice",
    say: Callable[[str], None] | None = None,
    settle_s: float = _SETTLE_S,
) -> Dispatcher:
    """A dispatcher publishing on ``bus`` that follows the rig's aid states (after ``settle_s`` [s])."""

    def publish(topic: str, payload: bytes, qos: int, retain: bool) -> None:
        bus.publish(topic, payload, qos=qos, retain=retain)

    dispatcher = Dispatcher(rig, publish, robot=robot, source=source, say=say)
    for stream in AID_STREAMS:
        bus.subscribe(Topic.pattern(rig, "+", stream), dispatcher.observe, qos=1)
    time.sleep(settle_s)
    return dispatcher


def say_text(dispatcher: Dispatcher, text: str, *, source: str | None = None) -> Reply:
    """One typed command through the grammar (``telerig say``)."""
    return dispatcher.handle(text, source=source)


def microphone(seconds: float = 3.0, *, program: str = "arecord") -> Iterator[bytes]:
    """WAV chunks of ``seconds`` [s] from the default microphone through ``arecord`` (ALSA), forever.

    Raises:
        DependencyError: ``arecord`` is missing (Debian package ``alsa-utils``).
        DeviceError: the recording failed (no microphone).
    """
    path = shutil.which(program)
    if path is None:
        raise DependencyError(f"{program} is missing (microphone input): apt-get install alsa-utils")
    if not 0.5 <= seconds <= 15:
        raise ValueError(f"seconds per utterance must be in [0.5, 15], got {seconds}")
    while True:
        cmd = [path, "-q", "-f", "S16_LE", "-r", str(SAMPLE_RATE), "-c", "1", "-t", "wav"]
        cmd += ["-d", str(max(1, round(seconds))), "-"]
        done = subprocess.run(cmd, capture_output=True, timeout=seconds + 10, check=False)
        if done.returncode != 0:
            why = done.stderr.decode(errors="replace").strip().splitlines()[:1]
            raise DeviceError(f"{program} failed: {why[0] if why else f'exit {done.returncode}'}")
        yield done.stdout


def listen(dispatcher: Dispatcher, recognizer: Recognizer, audio: Iterable[Path | bytes]) -> list[Reply]:
    """Recognize each utterance (a WAV path or WAV bytes) and dispatch what was heard.

    Bad audio, and speech that is not a command phrase (out of grammar, or too unlike the phrase it
    was forced onto: :func:`~telerig.voice.recognizer.verdict`), are rejected with their one-line
    reason (said back and counted, nothing sent); silence is skipped.
    """
    replies = []
    for utterance in audio:
        try:
            heard = recognizer.recognize_wav(utterance)
        except DeviceError as exc:
            replies.append(dispatcher.reject("", str(exc)))
            continue
        if heard.command:
            replies.append(dispatcher.handle(heard.text, source="voice"))
        elif heard.reason is not None:
            replies.append(dispatcher.reject(heard.text, heard.reason, source="voice"))
    return replies
