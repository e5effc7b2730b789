"""Builds the placedb package (pyproject.toml has its metadata).

The messages and gRPC stubs (``placedb._pb``) are generated at build time from the repository's
``proto/placedb.proto`` and ``proto/health.proto``, never committed, the same way
client/python/CMakeLists.txt does it: protoc (Debian's protobuf-compiler) with
grpc_python_plugin (protobuf-compiler-grpc), whose generated code matches Debian's
python3-protobuf. Without those, ``python3 -m grpc_tools.protoc`` (grpcio-tools) is used;
Debian 12's python3-grpc-tools bundles protoc 3.5, too old for the proto's ``optional`` fields.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import List

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = Path(__file__).resolve().parent
PROTOS = {
    "placedb.proto": HERE.parent.parent / "proto" / "placedb.proto",
    "health.proto": HERE.parent.parent / "proto" / "health.proto",
}


def _generator() -> List[str]:
    """The protoc command line's start: protoc + grpc_python_plugin, else grpc_tools.protoc."""
    protoc = shutil.which("protoc")
    plugin = shutil.which("grpc_python_plugin")
    if protoc and plugin:
        return [protoc, f"--plugin=protoc-gen-grpc_python={plugin}"]
    try:
        import grpc_tools.protoc  # noqa: F401
    except ImportError:
        sys.exit(
            "placedb: generating the gRPC stubs needs protoc and grpc_python_plugin "
            "(apt-get install protobuf-compiler protobuf-compiler-grpc) or grpcio-tools"
        )
    return [sys.executable, "-m", "grpc_tools.protoc"]


def generate_stubs(package_root: Path) -> List[Path]:
    """Writes placedb/_pb (the .proto files, their messages and stubs) under package_root."""
    for name, path in PROTOS.items():
        if not path.is_file():
            sys.exit(
                f"placedb: {path} is missing: build the package from a placedb checkout "
                f"(pip install ./client/python), which holds proto/ beside client/"
            )
    with tempfile.TemporaryDirectory(prefix="placedb-protoc-") as stage:
        # Staged as placedb/_pb/*.proto so the generated imports read "from placedb._pb import".
        staged = Path(stage) / "placedb" / "_pb"
        staged.mkdir(parents=True)
        for name, path in PROTOS.items():
            shutil.copyfile(path, staged / name)
        out = package_root / "placedb" / "_pb"
        out.mkdir(parents=True, exist_ok=True)
        command = _generator() + [
            f"--proto_path={stage}",
            f"--python_out={package_root}",
            f"--grpc_python_out={package_root}",
        ]
        command += [f"placedb/_pb/{name}" for name in PROTOS]
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode != 0:
            sys.exit(f"placedb: {' '.join(command)} failed:\n{done.stderr}")
        for name in PROTOS:
            shutil.copyfile(staged / name, out / name)
    (out / "__init__.py").write_text('"""Generated from proto/placedb.proto at build time."""\n')
    return sorted(out.iterdir())


class BuildPyWithStubs(build_py):
    """build_py, then the generated placedb._pb next to the package's sources."""

    def run(self) -> None:
        super().run()
        self._generated = generate_stubs(Path(self.build_lib))

    def get_outputs(self, include_bytecode: bool = True) -> List[str]:
        return super().get_outputs(include_bytecode) + [
            str(path) for path in getattr(self, "_generated", [])
        ]


setup(cmdclass={"build_py": BuildPyWithStubs})
