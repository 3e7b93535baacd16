"""Voice commands: recognition of every phrasing, rejection of speech that is no command, decode time.

Speech is synthesized by espeak-ng (en-us) at several speaking rates and fed to
:class:`telerig.voice.recognizer.Recognizer` (pocketsphinx 5, JSGF of the grammar). Measured per rate:

* in-grammar: a phrasing is recognized when the recognizer accepts it as that command. *before*:
  what the grammar decoder alone gives (any full phrase counts, the score rule off); *baseline*: the
  raw decoder without the recognizer's level normalization and padding.
* out of grammar (:data:`OUT_OF_GRAMMAR`: everyday sentences, near misses of commands, single words,
  numbers; plus :func:`noises` once): rejected when the recognizer does not accept a command;
  *before*: rejected only when no full phrase came out.
* critical: out-of-grammar utterances accepted as a critical command (only ever staged, said back)
  and as the confirmation "robot please execute" (which would run a staged one): must be none.

Before and after come from the same decode: the recognizer keeps the decoder's phrase in
``Heard.text`` and decides acceptance from the words' acoustic scores (:func:`verdict`). The plot
shows those scores against the thresholds.

Usage: python benchmarks/voice_recognition.py [--wpm 125,140,160]
       [--json benchmarks/results/voice_recognition.json] [--plot benchmarks/results/voice_recognition.png]
"""

from __future__ import annotations

import argparse
import io
import json
import platform
import time
import wave
from pathlib import Path
from typing import Any

import numpy as np

from telerig.ir.types import FloatArray
from telerig.voice.feedback import synthesize
from telerig.voice.grammar import COMMANDS, CONFIRMATION, Command, parse
from telerig.voice.recognizer import (
    MIN_CONFIRM_WORD_SCORE,
    MIN_SCORE,
    SAMPLE_RATE,
    Heard,
    Recognizer,
    jsgf,
    read_wav,
)

#: Speech that is no command, by kind (espeak-ng); near misses share words with phrases.
OUT_OF_GRAMMAR: dict[str, list[str]] = {
    "everyday": [
        "what a lovely day", "please pass me the salt", "what is the weather today", "open the door",
        "I think we should have lunch now", "can you hear me", "hello there", "good morning everyone",
        "the meeting starts at three o'clock", "turn left at the next corner", "I don't know what to do",
        "where did I put my keys", "thank you very much", "let me think about it", "please stop talking",
        "this is a very long sentence about nothing in particular that keeps going on and on and on",
    ],
    "near miss": [
        "robot please move", "please execute", "execute", "robot please", "robot execute",
        "robot please excuse me", "robot please wait", "release", "reset", "release the brakes",
        "start the engine", "keep going", "navigate", "manipulate the cube", "record the music",
        "stop the music", "clear the table", "scale the wall",
    ],
    "single word": ["scale", "stop", "perspective", "episode", "yes", "no", "okay", "emergency", "shoulder"],
    "number": ["one two three four", "forty two", "seven", "twenty five percent", "three point one four"],
}  # fmt: skip


def _wav(samples: np.ndarray) -> bytes:
    buf = io.BytesIO()
    with wave.open(buf, "wb") as w:
        w.setnchannels(1)
        w.setsampwidth(2)
        w.setframerate(SAMPLE_RATE)
        w.writeframes(np.clip(np.round(samples), -32768, 32767).astype("<i2").tobytes())
    return buf.getvalue()


def noises() -> dict[str, bytes]:
    """Non-speech audio (WAV, 16 kHz): noise, hum, clicks, a tone sweep, speech played backwards."""
    rng = np.random.default_rng(3)
    n = 2 * SAMPLE_RATE
    t = np.arange(n) / SAMPLE_RATE
    white = rng.normal(0, 6000, n)
    pink = np.cumsum(rng.normal(0, 1, n))
    pink = (pink - np.convolve(pink, np.ones(400) / 400, mode="same")) * 2000
    backwards = read_wav(synthesize("please pass me the salt and the pepper"))[::-1]
    return {
        "white noise": _wav(white),
        "low-passed noise": _wav(pink),
        "50 Hz hum": _wav(15_000 * np.sin(2 * np.pi * 50 * t)),
        "clicks": _wav(np.where(np.arange(n) % 1600 < 8, 30_000, 0)),
        "tone sweep": _wav(10_000 * np.sin(2 * np.pi * (200 + 900 * t) * t)),
        "reversed speech": _wav(backwards),
        "faint noise 10 s": _wav(rng.normal(0, 200, 10 * SAMPLE_RATE)),
    }


def _raw_decoder() -> Any:
    from pocketsphinx import Decoder  # type: ignore[import-untyped]

    d = Decoder(lm=None, loglevel="FATAL")
    d.add_jsgf_string("commands", jsgf())
    d.activate_search("commands")
    return d


def _raw(decoder: Any, wav: bytes) -> str:
    samples = read_wav(wav).clip(-32768, 32767).astype("<i2").tobytes()
    decoder.start_utt()
    decoder.process_raw(samples, full_utt=True)
    decoder.end_utt()
    hyp = decoder.hyp()
    return "" if hyp is None else str(hyp.hypstr)


def _command(heard: Heard, *, rule: bool) -> Command | None:
    """The command accepted from ``heard``: with the score rule (after) or any full phrase (before)."""
    if rule and not heard.command:
        return None
    return parse(heard.text).command


def _out_of_grammar(recognizer: Recognizer, items: dict[str, list[tuple[str, bytes]]]) -> dict[str, Any]:
    """Rejection counts per kind, before and after, and the critical acceptances."""
    row: dict[str, Any] = {"kinds": {}, "critical": {"before": [], "after": []}, "scores": []}
    row["confirmed"] = {"before": [], "after": []}
    row["accepted_after"] = []
    for kind, wavs in items.items():
        before = after = 0
        for said, wav in wavs:
            heard = recognizer.recognize_wav(wav)
            for when, rule in (("before", False), ("after", True)):
                command = _command(heard, rule=rule)
                if command is None:
                    before += when == "before"
                    after += when == "after"
                    continue
                if when == "after":
                    row["accepted_after"].append(f"{said} -> {heard.text} ({heard.score:.2f})")
                if command.critical:
                    row["critical"][when].append(f"{said} -> {heard.text}")
                if command.name == "execute":
                    row["confirmed"][when].append(f"{said} -> {heard.text}")
            if heard.score is not None and parse(heard.text).command is not None:
                row["scores"].append([heard.score, heard.worst, heard.text == CONFIRMATION])
        row["kinds"][kind] = {"n": len(wavs), "rejected_before": before, "rejected_after": after}
    row["n"] = sum(k["n"] for k in row["kinds"].values())
    row["rejected_before"] = sum(k["rejected_before"] for k in row["kinds"].values())
    row["rejected_after"] = sum(k["rejected_after"] for k in row["kinds"].values())
    return row


def _sweep(in_scores: list[list[Any]], oog_scores: list[list[Any]], n_out: int) -> dict[str, Any]:
    """Accepted in-grammar and rejected out-of-grammar utterances at other values of MIN_SCORE.

    ``in_scores``: the utterances decoded as their own phrase; ``oog_scores``: those forced onto a
    full phrase (the rest is rejected at any threshold). Items: ``[score, worst, is_confirmation]``.
    """

    def passes(s: list[Any], t: float) -> bool:
        return bool(s[0] >= t and (not s[2] or s[1] >= MIN_CONFIRM_WORD_SCORE))

    out = []
    for t in (-6.0, -5.0, -4.5, -4.25, -4.0, -3.5, -3.0):
        accepted = sum(passes(s, t) for s in in_scores)
        rejected = n_out - sum(passes(s, t) for s in oog_scores)
        out.append((t, accepted, rejected))
    return {"n_in": len(in_scores), "n_out": n_out, "rows": out}


def _clip(xs: list[float]) -> FloatArray:
    out: FloatArray = np.clip(np.asarray(xs, dtype=np.float64), -10.0, 0.0)
    return out


def _plot(path: Path, in_scores: list[list[Any]], oog_scores: list[list[Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    bins = np.linspace(-10, 0, 41)
    a.hist(_clip([s[0] for s in in_scores]), bins, alpha=0.6, label="in grammar (right phrase)")
    a.hist(_clip([s[0] for s in oog_scores]), bins, alpha=0.6, label="out of grammar (forced onto a phrase)")
    a.axvline(MIN_SCORE, color="k", ls="--", label=f"MIN_SCORE {MIN_SCORE}")
    a.set(xlabel="mean word score [nats/frame] (clipped at -10)", ylabel="utterances", title="any phrase")
    a.legend(fontsize=8)
    b.hist(_clip([s[1] for s in in_scores if s[2]]), bins, alpha=0.6, label="'robot please execute' said")
    b.hist(_clip([s[1] for s in oog_scores if s[2]]), bins, alpha=0.6, label="out of grammar heard as it")
    b.axvline(MIN_CONFIRM_WORD_SCORE, color="k", ls="--", label=f"confirmation {MIN_CONFIRM_WORD_SCORE}")
    b.set(xlabel="worst word score [nats/frame]", title="the confirmation")
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--wpm", default="125,140,160", help="speaking rates [words/min], comma-separated")
    ap.add_argument("--json", type=Path, default=Path("benchmarks/results/voice_recognition.json"))
    ap.add_argument("--plot", type=Path, default=Path("benchmarks/results/voice_recognition.png"))
    args = ap.parse_args()
    rates = [int(w) for w in args.wpm.split(",")]
    recognizer, raw = Recognizer(), _raw_decoder()
    rows: list[dict[str, Any]] = []
    misses: list[dict[str, Any]] = []
    in_scores: list[list[Any]] = []
    oog_scores: list[list[Any]] = []
    for wpm in rates:
        ok = before_ok = base_ok = n = 0
        decode_s = 0.0
        for command in COMMANDS:
            for phrase in command.phrases:
                wav = synthesize(phrase, wpm=wpm)
                t = time.perf_counter()
                heard = recognizer.recognize_wav(wav)
                decode_s += time.perf_counter() - t
                n += 1
                ok += _command(heard, rule=True) is command
                before_ok += _command(heard, rule=False) is command
                base_ok += parse(_raw(raw, wav)).command is command
                if _command(heard, rule=False) is command:
                    in_scores.append([heard.score, heard.worst, heard.text == CONFIRMATION])
                if _command(heard, rule=True) is not command:
                    misses.append({"wpm": wpm, "phrase": phrase, "heard": heard.text, "reason": heard.reason})
        items = {k: [(p, synthesize(p, wpm=wpm)) for p in ps] for k, ps in OUT_OF_GRAMMAR.items()}
        oog = _out_of_grammar(recognizer, items)
        oog_scores += oog.pop("scores")
        print(f"  {wpm} wpm: {n} phrasings, {oog['n']} out of grammar decoded", flush=True)
        rows.append({
            "wpm": wpm, "phrasings": n, "recognized": ok, "recognized_before": before_ok,
            "baseline_recognized": base_ok, "decode_ms_per_utterance": 1000 * decode_s / n,
            "out_of_grammar": oog,
        })  # fmt: skip
    noise = _out_of_grammar(recognizer, {"noise": list(noises().items())})
    oog_scores += noise.pop("scores")
    print(
        f"rule: mean word score >= {MIN_SCORE}, confirmation words >= {MIN_CONFIRM_WORD_SCORE} [nats/frame]"
    )
    print(
        f"{'wpm':>5} {'in grammar after':>17} {'before':>7} {'raw':>4} {'ms/utt':>7} "
        f"{'out of grammar rejected':>24} {'before':>7} {'critical':>9} {'confirmed':>10}"
    )
    for r in [*rows, {"wpm": "noise", "out_of_grammar": noise}]:
        o = r["out_of_grammar"]
        head = (
            f"{r['recognized']:>10}/{r['phrasings']:<6} {r['recognized_before']:>7} "
            f"{r['baseline_recognized']:>4} "
            f"{r['decode_ms_per_utterance']:>7.0f}"
            if "phrasings" in r
            else f"{'':>17} {'':>7} {'':>4} {'':>7}"
        )
        print(
            f"{r['wpm']:>5} {head} {o['rejected_after']:>17}/{o['n']:<6} {o['rejected_before']:>7} "
            f"{len(o['critical']['after']):>4} ({len(o['critical']['before'])}) "
            f"{len(o['confirmed']['after']):>5} ({len(o['confirmed']['before'])})"
        )
    confirmed = [c for r in rows for c in r["out_of_grammar"]["confirmed"]["after"]]
    confirmed += noise["confirmed"]["after"]
    print("critical / confirmed: out-of-grammar utterances accepted as a critical command (staged only)")
    print(f"  / as the confirmation, after the rule (before in brackets); confirmed: {confirmed or 'none'}")
    sweep = _sweep(in_scores, oog_scores, sum(r["out_of_grammar"]["n"] for r in rows) + noise["n"])
    print("MIN_SCORE sweep (confirmation rule kept): threshold, in grammar accepted, out of grammar rejected")
    print("  " + ", ".join(f"{t}: {a}/{len(in_scores)} {r}/{sweep['n_out']}" for t, a, r in sweep["rows"]))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        "host": platform.node(), "python": platform.python_version(),
        "rule": {"min_score": MIN_SCORE, "min_confirm_word_score": MIN_CONFIRM_WORD_SCORE},
        "rows": rows, "noise": noise, "misses": misses, "min_score_sweep": sweep,
    }  # fmt: skip
    args.json.write_text(json.dumps(doc, indent=1) + "\n")
    _plot(args.plot, in_scores, oog_scores)
    print(f"wrote {args.json} and {args.plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
