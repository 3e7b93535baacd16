"""Spoken feedback with espeak-ng: say a command's status, or synthesize it to WAV (tests, demos)."""

from __future__ import annotations

import shutil
import subprocess

from telerig.errors import DependencyError, DeviceError

__all__ = ["ESPEAK", "Speaker", "synthesize"]

#: The espeak-ng program (Debian package ``espeak-ng``; scripts/system-deps.sh installs it).
ESPEAK = "espeak-ng"
_FIX = "install the espeak-ng program: apt-get install espeak-ng (or scripts/system-deps.sh)"
#: Longest text spoken [characters]: feedback is one short sentence.
_MAX_CHARS = 300


def _program() -> str:
    path = shutil.which(ESPEAK)
    if path is None:
        raise DependencyError(f"{ESPEAK} is missing (spoken feedback): {_FIX}")
    return path


def synthesize(text: str, *, voice: str = "en-us", wpm: int = 140, timeout_s: float = 10.0) -> bytes:
    """``text`` spoken by espeak-ng as a WAV file (16-bit mono PCM, 22 050 Hz).

    Args:
        text: What to say (at most 300 characters).
        voice: espeak-ng voice.
        wpm: Speaking rate [words/min], 80-300.
        timeout_s: Longest the program may take [s].

    Raises:
        DependencyError: espeak-ng is not installed (the message says how to install it).
        DeviceError: espeak-ng failed.
    """
    if not text.strip() or len(text) > _MAX_CHARS:
        raise ValueError(f"text to speak must be 1-{_MAX_CHARS} characters, got {len(text)}")
    if not 80 <= wpm <= 300:
        raise ValueError(f"wpm must be in [80, 300], got {wpm}")
    cmd = [_program(), "-v", voice, "-s", str(wpm), "--stdout", "--", text]
    try:
        done = subprocess.run(cmd, capture_output=True, timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired:
        raise DeviceError(f"{ESPEAK} took longer than {timeout_s} s") from None
    if done.returncode != 0 or not done.stdout.startswith(b"RIFF"):
        why = done.stderr.decode(errors="replace").strip().splitlines()[:1]
        raise DeviceError(f"{ESPEAK} failed (exit {done.returncode}): {why[0] if why else 'no WAV output'}")
    return _fix_sizes(done.stdout)


def _fix_sizes(wav: bytes) -> bytes:
    """The RIFF and data chunk sizes set to the real length (espeak-ng writes a stream's placeholders)."""
    at = wav.find(b"data", 12)
    if at < 0:
        raise DeviceError(f"{ESPEAK} wrote a WAV without a data chunk")
    data = len(wav) - at - 8
    out = bytearray(wav)
    out[4:8] = (len(wav) - 8).to_bytes(4, "little")
    out[at + 4 : at + 8] = data.to_bytes(4, "little")
    return bytes(out)


class Speaker:
    """Says feedback sentences through the sound card with espeak-ng, without waiting for them.

    A new sentence cuts the one still being spoken (the newest status is what matters).

    Args:
        voice: espeak-ng voice.
        wpm: Speaking rate [words/min].

    Raises:
        DependencyError: espeak-ng is not installed.
    """

    def __init__(self, *, voice: str = "en-us", wpm: int = 160) -> None:
        self._program = _program()
        self._voice = voice
        self._wpm = wpm
        self._process: subprocess.Popen[bytes] | None = None

    def say(self, text: str) -> None:
        """Start speaking ``text`` (the first 300 characters)."""
        self.close()
        self._process = subprocess.Popen(
            [self._program, "-v", self._voice, "-s", str(self._wpm), "--", text[:_MAX_CHARS]],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )

    def close(self) -> None:
        """Stop speaking. Idempotent."""
        process, self._process = self._process, None
        if process is not None and process.poll() is None:
            process.terminate()
            process.wait(timeout=5)
