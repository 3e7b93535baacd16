"""Offline speech recognition of the command grammar: pocketsphinx 5 with a JSGF grammar of its phrases.

The decoder only ever hears the grammar's phrases (its JSGF is generated from
:data:`~telerig.voice.grammar.COMMANDS`), so a hypothesis is either a phrase or a partial path the
grammar parser rejects. The wheel ships the US-English acoustic model and dictionary: nothing is
downloaded.

Audio is 16-bit PCM; it is mixed to mono, resampled to the model's 16 kHz, peak-normalized and
padded with silence before decoding. Why normalize: with espeak-ng speech at its default level
(peaks ~20 000 of 32 767) 26 of 31 grammar phrases were recognized, and 31 of 31 at speaking rates
125-160 wpm once peaks were scaled to 2 000 (the decoder's noise and silence estimates work on
absolute energy). Why pad: the first 0.4 s let batch CMN and the noise estimate see silence.
"""

from __future__ import annotations

import io
import math
import wave
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from telerig.errors import DependencyError, DeviceError
from telerig.ir.types import FloatArray
from telerig.voice.grammar import phrases

if TYPE_CHECKING:
    from pocketsphinx import Decoder  # type: ignore[import-untyped]  # no stubs or py.typed

__all__ = ["MAX_AUDIO_BYTES", "MAX_AUDIO_S", "SAMPLE_RATE", "Recognizer", "jsgf", "read_wav"]

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


class Recognizer:
    """Decodes one utterance at a time into the grammar phrase it most likely is.

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
        #: Utterances decoded, and those that were silence (not decoded).
        self.decoded = 0
        self.silent = 0

    def recognize(self, samples: FloatArray) -> str:
        """The words heard in ``samples`` (mono, :data:`SAMPLE_RATE`, PCM16 scale); ``""`` for silence
        or when no phrase fits. A partial phrase may come back: the grammar parser rejects it."""
        audio = _prepare(np.asarray(samples, dtype=np.float64))
        if audio is None:
            self.silent += 1
            return ""
        d = self._decoder
        d.start_utt()
        try:
            d.process_raw(audio, full_utt=True)
        finally:
            d.end_utt()  # an interrupted utterance must not block the next one
        self.decoded += 1
        hyp = d.hyp()
        return "" if hyp is None else str(hyp.hypstr)

    def recognize_wav(self, source: Path | bytes) -> str:
        """:meth:`recognize` of a WAV file (see :func:`read_wav` for what it accepts)."""
        return self.recognize(read_wav(source))
