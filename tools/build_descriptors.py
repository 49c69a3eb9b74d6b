"""Compile starlog's ``.proto`` sources (``schemas/starlog/*.proto``) into the FileDescriptorSet it embeds in logs.

starlog does not generate ``_pb2.py`` modules (they couple to the protobuf runtime's version): at run
time it builds its message classes from this descriptor set (:mod:`starlog.codecs.star_tables`), and each
protobuf channel's schema is the part of it that defines the channel's message. protoc comes from
grpcio-tools (the test extra); ``tests/test_star_tables.py`` compiles the sources again and compares,
so the sources and the committed ``schemas/starlog.desc`` never drift apart.

Usage::

    python tools/build_descriptors.py           # rewrite schemas/starlog.desc
    python tools/build_descriptors.py --check   # exit 1 when schemas/starlog.desc is not what the sources give
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

SCHEMAS = Path(__file__).resolve().parent.parent / "schemas"
DESCRIPTORS = SCHEMAS / "starlog.desc"


def compile_descriptors(schemas: Path = SCHEMAS) -> bytes:
    """The FileDescriptorSet of every ``starlog/*.proto`` under ``schemas``, in file-name order, without source
    info (comments stay in the sources)."""
    import grpc_tools
    from grpc_tools import protoc

    sources = sorted(p.relative_to(schemas).as_posix() for p in (schemas / "starlog").glob("*.proto"))
    if not sources:
        raise FileNotFoundError(f"no .proto files under {schemas / 'starlog'}")
    include = Path(grpc_tools.__file__).resolve().parent / "_proto"  # the well-known types protoc ships
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "set.desc"
        status = protoc.main(["protoc", f"-I{schemas}", f"-I{include}", f"--descriptor_set_out={out}", *sources])
        if status != 0:
            raise RuntimeError(f"protoc failed (exit {status}) on {', '.join(sources)}")
        return out.read_bytes()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true", help="compare instead of writing")
    args = parser.parse_args()
    data = compile_descriptors()
    if args.check:
        same = DESCRIPTORS.is_file() and DESCRIPTORS.read_bytes() == data
        print(f"{DESCRIPTORS.name}: {'up to date' if same else 'differs from the sources'}")
        return 0 if same else 1
    DESCRIPTORS.write_bytes(data)
    print(f"wrote {DESCRIPTORS} ({len(data)} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
