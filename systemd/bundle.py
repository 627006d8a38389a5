"""Build the offline install bundle of one architecture: ``make dist`` runs this per arch.

dist/sowgate-<version>-linux-<arch>.tar.gz holds everything a cab box with Debian 12's (or
Raspberry Pi OS 12's) own python3 needs, with no network: the sowgate wheel, every runtime
dependency as a wheel at exactly the version in constraints.txt (the versions every test and
benchmark ran with, not the wheel's ranges), the systemd units, the udev rule, the example
configs and install.sh. Wheels are fetched for the target (CPython 3.11, glibc manylinux up to
Debian 12's 2.36), not for the machine building the bundle, so an x86_64 PC builds the aarch64
bundle too. Only binary wheels are accepted: a dependency without one for the target would
need a compiler on the cab box, and this fails naming it instead.

    python systemd/bundle.py --wheel dist/sowgate-0.1.0-py3-none-any.whl --arch aarch64
"""

from __future__ import annotations

import argparse
import hashlib
import io
import re
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ARCHES = ("x86_64", "aarch64")
PYTHON = "3.11"  # Debian 12 and Raspberry Pi OS 12 (bookworm)
GLIBC_MINOR = 36  # bookworm's glibc 2.36: wheels for any manylinux_2_17 .. 2_36 run there

# bundle path -> source in the checkout (besides the wheels and the generated files)
FILES = {
    "install.sh": "systemd/install.sh",
    "constraints.txt": "constraints.txt",
    "systemd/sowgate.service": "systemd/sowgate.service",
    "systemd/sowgate-dashboard.service": "systemd/sowgate-dashboard.service",
    "systemd/README.md": "systemd/README.md",
    "udev/99-sowgate.rules": "systemd/99-sowgate.rules",
    "examples/sowgate.toml": "examples/sowgate.toml",
    "examples/sowgate-can-drill.toml": "examples/sowgate-can-drill.toml",
}


def platforms(arch: str) -> list[str]:
    """pip's --platform list for a bookworm box: one tag per glibc minor (pip does not expand
    manylinux_2_x downwards by itself) plus the legacy manylinux2014 alias."""
    tags = [f"manylinux_2_{minor}_{arch}" for minor in range(17, GLIBC_MINOR + 1)]
    return [*tags, f"manylinux2014_{arch}"]


def wheel_version(wheel: Path) -> tuple[str, str]:
    """(normalised project name, version) from a wheel's file name."""
    name, version = wheel.name.split("-")[:2]
    return normalise(name), version


def normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def pins(constraints: Path) -> dict[str, str]:
    out = {}
    for line in constraints.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if "==" in line:
            name, version = line.split("==", 1)
            out[normalise(name)] = version.strip()
    return out


def download(wheel: Path, arch: str, dest: Path, constraints: Path) -> list[Path]:
    """The sowgate wheel's runtime dependencies for ``arch``, pinned by ``constraints``."""
    dest.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--disable-pip-version-check",
           "--only-binary=:all:", "--python-version", PYTHON, "--implementation", "cp",
           "--abi", "cp311", "--abi", "abi3", "--abi", "none",
           "--constraint", str(constraints), "--dest", str(dest), str(wheel)]
    for tag in platforms(arch):
        cmd[4:4] = ["--platform", tag]
    result = subprocess.run(cmd, capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"bundle: no wheel for {arch} of some dependency:\n{result.stderr}")
    return sorted(p for p in dest.glob("*.whl") if p.name != wheel.name)


def check_pinned(wheels: list[Path], constraints: Path) -> None:
    """Every dependency at exactly its constraints.txt version (a stale cache could hold an
    older download next to the new one)."""
    pinned = pins(constraints)
    for whl in wheels:
        name, version = wheel_version(whl)
        if pinned.get(name) != version:
            raise SystemExit(f"bundle: {whl.name} is not the version constraints.txt pins "
                             f"({name}=={pinned.get(name)})")


def build(wheel: Path, arch: str, out_dir: Path, cache: Path) -> Path:
    """Download the dependencies of ``wheel`` for ``arch`` (cached) and write its bundle."""
    constraints = REPO / "constraints.txt"
    # one cache folder per constraints.txt content: a re-lock never mixes versions
    digest = hashlib.sha256(constraints.read_bytes()).hexdigest()[:12]
    deps = download(wheel, arch, cache / f"{arch}-{digest}", constraints)
    check_pinned(deps, constraints)
    return write_bundle(out_dir, wheel_version(wheel)[1], arch, [wheel, *deps])


def write_bundle(out_dir: Path, version: str, arch: str, wheels: list[Path]) -> Path:
    """dist/sowgate-<version>-linux-<arch>.tar.gz: one top folder, reproducible (mtime 0),
    SHA256SUMS over every other file (install.sh checks it before installing anything)."""
    top = f"sowgate-{version}-linux-{arch}"
    members: dict[str, bytes] = {f"wheels/{whl.name}": whl.read_bytes() for whl in wheels}
    for name, source in FILES.items():
        members[name] = (REPO / source).read_bytes()
    members["BUNDLE"] = f"VERSION={version}\nARCH={arch}\n".encode()
    sums = "".join(f"{hashlib.sha256(data).hexdigest()}  {name}\n"
                   for name, data in sorted(members.items()))
    members["SHA256SUMS"] = sums.encode()
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / f"{top}.tar.gz"
    tmp = target.with_suffix(".tmp")
    with tarfile.open(tmp, "w:gz") as tar:
        for name, data in sorted(members.items()):
            info = tarfile.TarInfo(f"{top}/{name}")
            info.size = len(data)
            info.mode = 0o755 if name == "install.sh" else 0o644
            info.mtime = 0
            tar.addfile(info, io.BytesIO(data))
    tmp.replace(target)
    return target


def native_wheels(wheels: list[Path]) -> list[str]:
    """Dependencies with compiled code (a platform wheel, not pure Python), as name==version."""
    return sorted("{}=={}".format(*wheel_version(w)) for w in wheels
                  if not w.name.endswith("-none-any.whl"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--wheel", type=Path, required=True, help="the sowgate wheel")
    parser.add_argument("--arch", choices=ARCHES, action="append", required=True)
    parser.add_argument("--out", type=Path, default=REPO / "dist")
    parser.add_argument("--cache", type=Path, default=REPO / "build" / "dist-wheels")
    args = parser.parse_args(argv)
    if not zipfile.is_zipfile(args.wheel):
        parser.error(f"{args.wheel} is not a wheel")
    for arch in args.arch:
        target = build(args.wheel, arch, args.out, args.cache)
        with tarfile.open(target) as tar:
            names = [Path(n) for n in tar.getnames() if n.endswith(".whl")]
        print(f"{target} ({target.stat().st_size / 1e6:.0f} MB, {len(names)} wheels; "
              f"compiled for {arch}: {', '.join(native_wheels(names)) or 'none'})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
