"""Regenerate (or ``--check``) the committed Python code for ``ir.proto`` with grpc_tools.protoc."""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

__all__ = ["GENERATED_FILES", "PB_DIR", "PROTO_FILE", "PROTO_ROOT", "generate", "main", "stale_files"]

_IR_DIR = Path(__file__).resolve().parent
#: Include root of the .proto files; import paths in the schema are relative to it.
PROTO_ROOT = _IR_DIR / "proto"
#: The wire schema, relative to :data:`PROTO_ROOT`.
PROTO_FILE = "telerig/v1/ir.proto"
#: Where the generated modules are committed.
PB_DIR = _IR_DIR / "_pb"
#: Generated file names inside :data:`PB_DIR`.
GENERATED_FILES = ("ir_pb2.py", "ir_pb2.pyi")

# protoc names the module after the .proto path; it lives at telerig.ir._pb instead.
_PROTOC_MODULE = "'telerig.v1.ir_pb2'"
_OUR_MODULE = "'telerig.ir._pb.ir_pb2'"


def generate() -> dict[str, bytes]:
    """Run protoc on :data:`PROTO_FILE` and return ``{file name: content}`` for :data:`GENERATED_FILES`."""
    try:
        from grpc_tools import protoc
    except ImportError as exc:
        from telerig.errors import DependencyError

        raise DependencyError("grpcio-tools is missing: pip install -e '.[dev]'") from exc

    with tempfile.TemporaryDirectory() as tmp:
        args = [
            "protoc",
            f"-I{PROTO_ROOT}",
            f"--python_out={tmp}",
            f"--pyi_out={tmp}",
            PROTO_FILE,
        ]
        rc = protoc.main(args)
        if rc != 0:
            raise RuntimeError(f"protoc failed with exit code {rc} on {PROTO_ROOT / PROTO_FILE}")
        out_dir = Path(tmp) / Path(PROTO_FILE).parent
        files = {name: (out_dir / name).read_bytes() for name in GENERATED_FILES}
    files["ir_pb2.py"] = files["ir_pb2.py"].replace(_PROTOC_MODULE.encode(), _OUR_MODULE.encode())
    return files


def stale_files() -> list[str]:
    """Return the generated files in :data:`PB_DIR` that are missing or differ from fresh protoc output."""
    return [
        name
        for name, content in generate().items()
        if not (PB_DIR / name).is_file() or (PB_DIR / name).read_bytes() != content
    ]


def main(argv: list[str] | None = None) -> int:
    """Command line entry point: write the generated code, or with ``--check`` report staleness."""
    parser = argparse.ArgumentParser(prog="python -m telerig.ir.protogen", description=__doc__)
    parser.add_argument(
        "--check", action="store_true", help="exit 1 if the committed code differs from protoc output"
    )
    args = parser.parse_args(argv)
    if args.check:
        stale = stale_files()
        if stale:
            print(
                f"generated code is stale: {', '.join(stale)} in {PB_DIR}; "
                "run `python -m telerig.ir.protogen`",
                file=sys.stderr,
            )
            return 1
        print(f"generated code in {PB_DIR} is up to date")
        return 0
    PB_DIR.mkdir(exist_ok=True)
    for name, content in generate().items():
        (PB_DIR / name).write_bytes(content)
    print(f"wrote {', '.join(GENERATED_FILES)} to {PB_DIR}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
