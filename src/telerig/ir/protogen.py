"""Regenerate (or ``--check``) the committed Python code for every ``.proto`` schema with protoc."""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

__all__ = [
    "GENERATED_FILES",
    "PB_DIR",
    "PROTO_FILE",
    "PROTO_FILES",
    "PROTO_ROOT",
    "generate",
    "main",
    "stale_files",
]

_IR_DIR = Path(__file__).resolve().parent
#: Include root of the .proto files; import paths in the schema are relative to it.
PROTO_ROOT = _IR_DIR / "proto"
#: The IR wire schema, relative to :data:`PROTO_ROOT`.
PROTO_FILE = "telerig/v1/ir.proto"
#: Every schema compiled, relative to :data:`PROTO_ROOT`: all ``.proto`` files in ``telerig/v1``.
PROTO_FILES: tuple[str, ...] = tuple(
    sorted(p.relative_to(PROTO_ROOT).as_posix() for p in (PROTO_ROOT / "telerig" / "v1").glob("*.proto"))
)
#: Where the generated modules are committed.
PB_DIR = _IR_DIR / "_pb"
#: Generated file names inside :data:`PB_DIR`: ``<stem>_pb2.py`` and ``<stem>_pb2.pyi`` per schema.
GENERATED_FILES: tuple[str, ...] = tuple(
    f"{Path(proto).stem}_pb2{suffix}" for proto in PROTO_FILES for suffix in (".py", ".pyi")
)

# protoc names a module after its .proto path (telerig.v1.<stem>_pb2); they live at telerig.ir._pb.
_PROTOC_PACKAGE = "telerig.v1."
_OUR_PACKAGE = "telerig.ir._pb."


def generate() -> dict[str, bytes]:
    """Run protoc on :data:`PROTO_FILES` and return ``{file name: content}`` for :data:`GENERATED_FILES`."""
    try:
        from grpc_tools import protoc
    except ImportError as exc:
        from telerig.errors import DependencyError

        raise DependencyError("grpcio-tools is missing: pip install -e '.[dev]'") from exc

    with tempfile.TemporaryDirectory() as tmp:
        args = ["protoc", f"-I{PROTO_ROOT}", f"--python_out={tmp}", f"--pyi_out={tmp}", *PROTO_FILES]
        rc = protoc.main(args)
        if rc != 0:
            raise RuntimeError(
                f"protoc failed with exit code {rc} on {', '.join(PROTO_FILES)} in {PROTO_ROOT}"
            )
        files: dict[str, bytes] = {}
        for proto in PROTO_FILES:
            out_dir = Path(tmp) / Path(proto).parent
            stem = Path(proto).stem
            for suffix in (".py", ".pyi"):
                files[f"{stem}_pb2{suffix}"] = (out_dir / f"{stem}_pb2{suffix}").read_bytes()
    for name, content in files.items():
        if name.endswith(".py"):
            module = name.removesuffix(".py")
            files[name] = content.replace(
                f"'{_PROTOC_PACKAGE}{module}'".encode(), f"'{_OUR_PACKAGE}{module}'".encode()
            )
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
