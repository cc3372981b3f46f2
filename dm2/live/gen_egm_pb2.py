"""Regenerate ``egm_pb2.py`` and ``egm_rw6_pb2.py`` from ``egm.proto`` (RobotWare 7) and
``egm_rw6.proto`` (needs grpcio-tools, a development extra; not a runtime dependency).

Run from anywhere: ``python dm2/live/gen_egm_pb2.py``. The generated module is committed, so
running the project needs only the ``protobuf`` runtime, never protoc.
"""

from __future__ import annotations

import sys
from pathlib import Path


def main() -> int:
    try:
        from grpc_tools import protoc
    except ImportError:
        sys.stderr.write("gen_egm_pb2: needs grpcio-tools (pip install grpcio-tools)\n")
        return 2
    here = Path(__file__).resolve().parent
    rc = protoc.main(["protoc", f"-I{here}", f"--python_out={here}", str(here / "egm.proto"),
                      str(here / "egm_rw6.proto")])
    if rc != 0:
        sys.stderr.write(f"gen_egm_pb2: protoc failed with exit code {rc}\n")
    return rc


if __name__ == "__main__":
    sys.exit(main())
