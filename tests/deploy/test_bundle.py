"""What ``make dist`` puts in a bundle (systemd/bundle.py), without the network.

The real bundles' dependency download is exercised by `make dist` and installed by
`make system-test`; here: the layout install.sh relies on, the checksums, the platforms asked
for, and that nothing but constraints.txt's exact versions can get in.
"""

from __future__ import annotations

import hashlib
import re
import tarfile
from pathlib import Path

import pytest

from tests.deploy import bundle
from tests.deploy.fake_bundle import make_bundle

REPO = Path(__file__).resolve().parents[2]


def test_the_bundle_holds_wheels_units_rule_examples_installer_and_checksums(
    tmp_path: Path,
) -> None:
    folder = make_bundle(tmp_path, "2.0.0", arch="aarch64")
    assert folder.name == "sowgate-2.0.0-linux-aarch64"
    with tarfile.open(tmp_path / "sowgate-2.0.0-linux-aarch64.tar.gz") as tar:
        names = {m.name.split("/", 1)[1]: m for m in tar.getmembers()}
    assert set(names) == {*bundle.FILES, "BUNDLE", "SHA256SUMS",
                          "wheels/sowgate-2.0.0-py3-none-any.whl",
                          "wheels/sowgate_fake_dep-1.0-py3-none-any.whl"}
    assert names["install.sh"].mode == 0o755
    for name, source in bundle.FILES.items():
        assert (folder / name).read_bytes() == (REPO / source).read_bytes(), name
    assert (folder / "BUNDLE").read_text() == "VERSION=2.0.0\nARCH=aarch64\n"
    sums = dict(reversed(line.split("  ")) for line in
                (folder / "SHA256SUMS").read_text().splitlines())
    assert set(sums) == set(names) - {"SHA256SUMS"}
    for name, digest in sums.items():
        assert hashlib.sha256((folder / name).read_bytes()).hexdigest() == digest, name


def test_bundles_are_reproducible(tmp_path: Path) -> None:
    one = make_bundle(tmp_path / "1", "2.0.0").parent / f"sowgate-2.0.0-linux-{_arch()}.tar.gz"
    two = make_bundle(tmp_path / "2", "2.0.0").parent / f"sowgate-2.0.0-linux-{_arch()}.tar.gz"
    # same content, same members (gzip headers carry the file name, so compare the tar)
    with tarfile.open(one) as a, tarfile.open(two) as b:
        assert [(m.name, m.mtime, m.mode) for m in a] == [(m.name, m.mtime, m.mode) for m in b]


def _arch() -> str:
    import platform

    return platform.machine()


@pytest.mark.parametrize("arch", bundle.ARCHES)
def test_wheels_are_asked_for_every_glibc_of_debian_12(arch: str) -> None:
    tags = bundle.platforms(arch)
    minors = sorted(int(m) for t in tags for m in re.findall(rf"manylinux_2_(\d+)_{arch}$", t))
    assert minors == list(range(17, 37))  # 2.17 (manylinux2014) .. 2.36 (bookworm)
    assert f"manylinux2014_{arch}" in tags


def test_only_the_versions_in_constraints_get_in(tmp_path: Path) -> None:
    constraints = tmp_path / "constraints.txt"
    constraints.write_text("# pins\nnumpy==2.4.6\ntyping_extensions==4.16.0\n")
    good = [tmp_path / "numpy-2.4.6-cp311-cp311-manylinux_2_28_aarch64.whl",
            tmp_path / "typing_extensions-4.16.0-py3-none-any.whl"]
    bundle.check_pinned(good, constraints)
    with pytest.raises(SystemExit, match=r"numpy-2.4.5.*\(numpy==2.4.6\)"):
        bundle.check_pinned([tmp_path / "numpy-2.4.5-cp311-cp311-manylinux_2_28_aarch64.whl"],
                            constraints)
    with pytest.raises(SystemExit, match=r"tzdata-2026.6.*\(tzdata==None\)"):
        bundle.check_pinned([tmp_path / "tzdata-2026.6-py2.py3-none-any.whl"], constraints)


def test_the_runtime_dependencies_are_all_pinned_in_constraints() -> None:
    """Every Requires-Dist of sowgate (not extras) has an exact pin: else a bundle would fail."""
    from importlib.metadata import requires

    pinned = bundle.pins(REPO / "constraints.txt")
    for req in requires("sowgate") or []:
        if "extra ==" in req:
            continue
        name = bundle.normalise(re.split(r"[\s\[<>=~!;]", req, maxsplit=1)[0])
        assert name in pinned, req
