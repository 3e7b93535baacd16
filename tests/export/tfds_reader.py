"""Read RLDS datasets with the real tensorflow-datasets (run in .venv-tfds by tests/export/test_rlds.py).

Usage: python tfds_reader.py OUT_DIR BUILDER_DIR...

For each builder directory, ``tfds.builder_from_directory(DIR).as_dataset(split="train")`` and,
per episode, one ``<OUT_DIR>/<dir index>-<episode id>.npz`` with every step field as TensorFlow
decoded it (images reduced to their per-step channel means plus three full frames), and
``<OUT_DIR>/<dir index>.json`` with the dataset's name, features and split lengths.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import tensorflow_datasets as tfds


def _flatten(tree: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}/"))
        else:
            out[f"{prefix}{key}"] = value
    return out


def main(out_dir: Path, builder_dirs: list[str]) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    for index, builder_dir in enumerate(builder_dirs):
        builder = tfds.builder_from_directory(builder_dir)
        split = builder.info.splits["train"]
        summary = {
            "name": builder.info.name,
            "version": str(builder.info.version),
            "num_examples": int(split.num_examples),
            "shard_lengths": [int(n) for n in split.shard_lengths],
            "episodes": [],
        }
        for episode in builder.as_dataset(split="train", shuffle_files=False):
            steps = episode["steps"].batch(1_000_000).get_single_element()
            arrays = {f"steps/{k}": v.numpy() for k, v in _flatten(steps).items()}
            arrays.update({f"meta/{k}": v.numpy() for k, v in episode["episode_metadata"].items()})
            for key, value in arrays.items():
                if isinstance(value, np.ndarray) and value.dtype == object:
                    arrays[key] = value.astype(bytes)  # strings, loadable without pickle
            for key in [k for k in arrays if "/image_" in k]:
                images = arrays.pop(key)
                arrays[f"{key}/shape"] = np.asarray(images.shape)
                arrays[f"{key}/dtype"] = np.asarray(str(images.dtype))
                arrays[f"{key}/mean"] = images.reshape(images.shape[0], -1, images.shape[-1]).mean(axis=1)
                picks = sorted({0, images.shape[0] // 2, images.shape[0] - 1})
                arrays[f"{key}/picks"] = np.asarray(picks)
                arrays[f"{key}/frames"] = images[picks]
            episode_id = arrays["meta/episode_id"].decode()
            summary["episodes"].append(episode_id)
            np.savez(out_dir / f"{index}-{episode_id}.npz", **arrays)
        (out_dir / f"{index}.json").write_text(json.dumps(summary))


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2:])
