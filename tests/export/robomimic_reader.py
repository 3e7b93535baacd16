"""Load a telerig robomimic export with robomimic's own loader; run by tests/export/test_robomimic.py
in .venv-robomimic (robomimic needs torch, which telerig's venv does not hold).

Usage: python robomimic_reader.py DATASET.hdf5

Prints one JSON line: per filter key, the demos robomimic selected, the sequences it indexed and the
shapes of one item, as ``robomimic.utils.dataset.SequenceDataset`` returns them.
"""

from __future__ import annotations

import inspect
import json
import sys

import h5py
from robomimic.utils import obs_utils
from robomimic.utils.dataset import SequenceDataset


def main(path: str) -> None:
    # What robomimic.utils.file_utils.get_env_metadata_from_dataset and
    # get_shape_metadata_from_dataset read (file_utils itself imports robomimic's algorithms, whose
    # dependencies, diffusers and torchvision among them, this venv does not hold).
    with h5py.File(path, "r") as f:
        env_meta = json.loads(f["data"].attrs["env_args"])
        first = f["data"][next(iter(f["data"]))]
        assert len(first["actions"].shape) == 2
        initial = {k: first["obs"][k].shape[1:] for k in first["obs"]}
    keys = list(env_meta["env_kwargs"]["obs_keys"])
    rgb = [k for k in keys if k.endswith("_image")]
    obs_utils.initialize_obs_utils_with_obs_specs(
        {"obs": {"low_dim": [k for k in keys if k not in rgb], "rgb": rgb}}
    )
    shapes = {
        k: list(
            obs_utils.get_processed_shape(
                obs_modality=obs_utils.OBS_KEYS_TO_MODALITIES[k], input_shape=initial[k]
            )
        )
        for k in keys
    }
    kwargs = {
        "hdf5_path": path,
        "obs_keys": keys,
        "dataset_keys": ["actions", "rewards", "dones"],
        "frame_stack": 1,
        "seq_length": 10,
        "hdf5_cache_mode": "low_dim",
        "hdf5_use_swmr": True,
        "load_next_obs": True,
    }
    if "action_keys" in inspect.signature(SequenceDataset.__init__).parameters:  # robomimic >= 0.4
        kwargs["action_keys"] = ["actions"]
        kwargs["action_config"] = {"actions": {"normalization": "min_max"}}
    report: dict[str, object] = {
        "env_name": env_meta["env_name"],
        "env_type": env_meta["type"],
        "shapes": shapes,
    }
    for filter_key in ("train", "valid", None):
        dataset = SequenceDataset(filter_by_attribute=filter_key, **kwargs)
        entry: dict[str, object] = {"demos": sorted(dataset.demos), "sequences": len(dataset)}
        if len(dataset):
            # The first and last sequence of every demo: each image is decoded from the file.
            items = [dataset[i] for i in sorted({0, len(dataset) - 1})]
            item = items[-1]
            entry["obs"] = {k: list(v.shape) for k, v in item["obs"].items()}
            entry["next_obs"] = {k: list(v.shape) for k, v in item["next_obs"].items()}
            entry["actions"] = list(item["actions"].shape)
            entry["image_dtype"] = [str(item["obs"][k].dtype) for k in rgb]
        report[str(filter_key)] = entry
    print(json.dumps(report))


if __name__ == "__main__":
    main(sys.argv[1])
