"""Generate the Python protobuf code for proto/rmmdet/v1/*.proto into proto/gen (gitignored).

Uses grpcio-tools' bundled protoc (Debian's protoc is too old for protobuf 7 gencode). The output
package is `rmmdet.v1`, importable because the editable install puts proto/gen on sys.path.
Run through `make proto`; `make install` runs it when a .proto changes.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

from grpc_tools import protoc

PROTO_DIR = Path(__file__).resolve().parent
GEN_DIR = PROTO_DIR / "gen"


def main() -> int:
    sources = sorted(str(p.relative_to(PROTO_DIR)) for p in (PROTO_DIR / "rmmdet").rglob("*.proto"))
    if not sources:
        print("no .proto files found", file=sys.stderr)
        return 1
    if GEN_DIR.exists():
        shutil.rmtree(GEN_DIR)
    GEN_DIR.mkdir(parents=True)
    well_known = Path(protoc.__file__).parent / "_proto"
    args = [
        "grpc_tools.protoc",
        f"-I{PROTO_DIR}",
        f"-I{well_known}",
        f"--python_out={GEN_DIR}",
        f"--pyi_out={GEN_DIR}",
        f"--descriptor_set_out={GEN_DIR / 'rmmdet_v1.binpb'}",
        "--include_imports",
        *sources,
    ]
    import os

    cwd = os.getcwd()
    os.chdir(PROTO_DIR)
    try:
        rc = protoc.main(args)
    finally:
        os.chdir(cwd)
    if rc != 0:
        print(f"protoc failed with exit code {rc}", file=sys.stderr)
        return rc
    for pkg in {p.parent for p in GEN_DIR.rglob("*_pb2.py")} | {GEN_DIR / "rmmdet"}:
        (pkg / "__init__.py").touch()
    (GEN_DIR / ".stamp").write_text("\n".join(sources) + "\n")
    print(f"generated {len(sources)} proto files into {GEN_DIR.relative_to(PROTO_DIR.parent)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
