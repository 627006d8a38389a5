"""Bundles like ``make dist``'s, around a stand-in sowgate wheel, for testing install.sh fast.

The real bundle's 48 wheels take ~25 s to install; install.sh does not care what sowgate
does, only that pip installs it and its dependencies offline and that ``sowgate --version``
and ``sowgate check-config`` answer. The stand-in answers like the real one (check-config:
exit 78 when the config says ``broken = true``; ``--systemd-device-allow``: a drop-in with the
config's ``port =`` lines) and depends on a second wheel, so a missing
dependency shows that nothing is fetched from a network.
"""

from __future__ import annotations

import base64
import hashlib
import platform
import tarfile
import zipfile
from pathlib import Path

from tests.deploy import bundle

write_bundle = bundle.write_bundle

DEPENDENCY = "sowgate_fake_dep"

_MODULE = '''\
import sys

VERSION = "{version}"


def main():
    args = sys.argv[1:]
    if args == ["--version"]:
        print("sowgate " + VERSION)
        return 0
    if args[:1] == ["check-config"]:
        dropin = "--systemd-device-allow" in args
        text = open([a for a in args[1:] if not a.startswith("--")][0]).read()
        if "broken = true" in text:
            print("machine.broken: not a key", file=sys.stderr)
            return 78
        if dropin:  # like the real one: the configured ports replace the unit's classes
            ports = [ln.split("=", 1)[1].split("#")[0].strip().strip('"')
                     for ln in text.splitlines() if ln.strip().startswith("port =")]
            print("[Service]\\nDeviceAllow="
                  + "".join("\\nDeviceAllow=" + p + " rw" for p in ports))
            return 0
        print(args[1] + ": ok")
        return 0
    return 64
'''


def _wheel(folder: Path, name: str, version: str, files: dict[str, str],
           requires: list[str], scripts: dict[str, str]) -> Path:
    info = f"{name}-{version}.dist-info"
    meta = ["Metadata-Version: 2.1", f"Name: {name}", f"Version: {version}"]
    meta += [f"Requires-Dist: {r}" for r in requires]
    contents = dict(files)
    contents[f"{info}/METADATA"] = "\n".join(meta) + "\n"
    contents[f"{info}/WHEEL"] = ("Wheel-Version: 1.0\nGenerator: tests\nRoot-Is-Purelib: true\n"
                                 "Tag: py3-none-any\n")
    if scripts:
        contents[f"{info}/entry_points.txt"] = "[console_scripts]\n" + "".join(
            f"{k} = {v}\n" for k, v in scripts.items())
    record = []
    for path, text in contents.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(text.encode()).digest()).rstrip(b"=")
        record.append(f"{path},sha256={digest.decode()},{len(text.encode())}")
    record.append(f"{info}/RECORD,,")
    contents[f"{info}/RECORD"] = "\n".join(record) + "\n"
    target = folder / f"{name}-{version}-py3-none-any.whl"
    with zipfile.ZipFile(target, "w") as whl:
        for path, text in contents.items():
            whl.writestr(path, text)
    return target


def make_bundle(out: Path, version: str, *, arch: str | None = None,
                with_dependency: bool = True, dep_version: str = "1.0") -> Path:
    """The unpacked bundle folder of a stand-in sowgate ``version``."""
    wheels = out / f"wheels-{version}"
    wheels.mkdir(parents=True)
    main = _wheel(wheels, "sowgate", version,
                  {"fake_sowgate.py": _MODULE.format(version=version)},
                  [f"{DEPENDENCY}=={dep_version}"], {"sowgate": "fake_sowgate:main"})
    dep = _wheel(wheels, DEPENDENCY, dep_version, {f"{DEPENDENCY}.py": "X = 1\n"}, [], {})
    tarball = write_bundle(out, version, arch or platform.machine(),
                           [main, dep] if with_dependency else [main])
    with tarfile.open(tarball) as tar:
        tar.extractall(out, filter="data")
    return out / tarball.name.removesuffix(".tar.gz")
