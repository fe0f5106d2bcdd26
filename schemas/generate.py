"""Regenerate the committed ``*_pb2.py`` modules from ``schemas/proto``.

Run ``make schemas`` (or ``python -m schemas.generate``) after editing a ``.proto``
file and commit the result.  ``tests/test_schemas.py`` regenerates into a temporary
folder and fails on any difference, so the committed modules never drift from the
protos.  The protoc used is the one bundled with ``grpcio-tools`` (pinned exactly in
``pyproject.toml``), so every machine generates the same bytes.
"""

from __future__ import annotations

import sys
from pathlib import Path

PROTO_ROOT = Path(__file__).resolve().parent / "proto"
OUTPUT_ROOT = Path(__file__).resolve().parent


def proto_files(root: Path = PROTO_ROOT) -> list[Path]:
    """All ``.proto`` files below ``root``, sorted, relative to ``root``."""
    return sorted(p.relative_to(root) for p in root.rglob("*.proto"))


def generate(output_root: Path = OUTPUT_ROOT, proto_root: Path = PROTO_ROOT) -> list[Path]:
    """Run protoc on every proto file; return the generated paths (relative to ``output_root``).

    Raises
    ------
    RuntimeError
        If protoc reports an error.
    """
    # deferred: grpc_tools (grpcio-tools) is a dev-only dependency, needed only to regenerate
    import grpc_tools
    from grpc_tools import protoc

    include = Path(grpc_tools.__file__).resolve().parent / "_proto"
    files = [str(p) for p in proto_files(proto_root)]
    args = [
        "protoc",
        f"-I{proto_root}",
        f"-I{include}",
        f"--python_out={output_root}",
        f"--pyi_out={output_root}",
        *files,
    ]
    code = protoc.main(args)
    if code != 0:
        raise RuntimeError(f"protoc failed with exit code {code}")
    out = []
    for f in files:
        stem = Path(f).with_suffix("")
        out += [Path(f"{stem}_pb2.py"), Path(f"{stem}_pb2.pyi")]
    return out


def main() -> int:
    for path in generate():
        print(f"generated schemas/{path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
