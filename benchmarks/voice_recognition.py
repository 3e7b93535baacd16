"""Voice commands: recognition of every phrasing of the grammar, and decode time per utterance.

Speech is synthesized by espeak-ng (en-us) at several speaking rates and fed to
:class:`telerig.voice.recognizer.Recognizer` (pocketsphinx 5, JSGF of the grammar). A phrasing is
recognized when the grammar parses what was heard to the same command. The baseline in the same run
is the raw decoder without the recognizer's level normalization and padding (espeak-ng's own level),
so the table shows what that preparation buys. Also: out-of-grammar phrases, whether any of them
came back as a *critical* command (only ever staged, never sent without "robot please execute").

Usage: python benchmarks/voice_recognition.py [--wpm 125,140,160]
       [--json benchmarks/results/voice_recognition.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path
from typing import Any

from telerig.voice.feedback import synthesize
from telerig.voice.grammar import COMMANDS, parse
from telerig.voice.recognizer import Recognizer, jsgf, read_wav

OUT_OF_GRAMMAR = [
    "what is the weather today", "robot please move", "open the door", "keep going", "release",
    "execute", "please execute", "robot please", "start the engine", "hello there",
]  # fmt: skip


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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--wpm", default="125,140,160", help="speaking rates [words/min], comma-separated")
    ap.add_argument("--json", type=Path, default=Path("benchmarks/results/voice_recognition.json"))
    args = ap.parse_args()
    rates = [int(w) for w in args.wpm.split(",")]
    recognizer, raw = Recognizer(), _raw_decoder()
    rows: list[dict[str, Any]] = []
    misses: list[dict[str, Any]] = []
    for wpm in rates:
        ok = base_ok = n = 0
        decode_s = 0.0
        for command in COMMANDS:
            for phrase in command.phrases:
                wav = synthesize(phrase, wpm=wpm)
                t = time.perf_counter()
                heard = recognizer.recognize_wav(wav)
                decode_s += time.perf_counter() - t
                n += 1
                ok += parse(heard).command is command
                base_ok += parse(_raw(raw, wav)).command is command
                if parse(heard).command is not command:
                    misses.append({"wpm": wpm, "phrase": phrase, "heard": heard})
        critical = [
            p
            for p in OUT_OF_GRAMMAR
            if (c := parse(recognizer.recognize_wav(synthesize(p, wpm=wpm))).command) and c.critical
        ]
        rows.append({
            "wpm": wpm, "phrasings": n, "recognized": ok, "baseline_recognized": base_ok,
            "ratio_vs_baseline": ok / base_ok if base_ok else None,
            "decode_ms_per_utterance": 1000 * decode_s / n, "out_of_grammar_heard_as_critical": critical,
        })  # fmt: skip
    print(f"{'wpm':>4} {'recognized':>11} {'baseline':>9} {'ms/utt':>7}  out of grammar -> critical")
    for r in rows:
        print(
            f"{r['wpm']:>4} {r['recognized']:>5}/{r['phrasings']:<5} {r['baseline_recognized']:>9} "
            f"{r['decode_ms_per_utterance']:>7.0f}  {', '.join(r['out_of_grammar_heard_as_critical']) or '-'}"
        )
    args.json.parent.mkdir(parents=True, exist_ok=True)
    doc = {"host": platform.node(), "python": platform.python_version(), "rows": rows, "misses": misses}
    args.json.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
