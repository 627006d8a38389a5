#!/bin/sh
# sowgate offline installer: run from the unpacked bundle (sowgate-<version>-linux-<arch>/).
#
#   sudo ./install.sh              install or upgrade to this bundle's version
#   sudo ./install.sh --rollback   go back to the version installed before the current one
#   ./install.sh --root DIR        the same into DIR (a fake root: tests, image builds); no
#                                  systemctl, no udevadm
#
# What it does, in this order (systemd/README.md "Install" says the same):
#  1. checks this box: the bundle's architecture, python3 >= 3.11 with venv (apt install
#     python3-venv), and that the bundle is complete (SHA256SUMS)
#  2. creates a virtualenv in /opt/sowgate/<version>/ and installs sowgate and every dependency
#     from the bundle's wheels only (pip --no-index: no network), at the versions of
#     constraints.txt (an upgrade starts from a copy of the current version's packages, so
#     pip installs only what differs); a half-built one never replaces a working one
#  3. copies the units, the udev rule and the example configs to /opt/sowgate/<version>/share
#  4. points /opt/sowgate/current at it and /usr/bin/sowgate at /opt/sowgate/current/bin/sowgate;
#     the version it replaces is kept as /opt/sowgate/previous (for --rollback), older ones
#     are removed
#  5. installs sowgate.service and sowgate-dashboard.service in /etc/systemd/system, and the
#     udev rule in /etc/udev/rules.d only if there is none yet (it holds your adapters' serials)
#  6. creates /etc/sowgate/sowgate.toml from the example only if there is none
#  7. runs `sowgate check-config /etc/sowgate/sowgate.toml`; a bad config: exit 78, the
#     service is left alone
#  8. writes /etc/systemd/system/sowgate.service.d/devices.conf from `sowgate check-config
#     --systemd-device-allow`: the unit's device classes narrowed to the configured ports
#  9. systemctl daemon-reload, enable and restart sowgate (and restart the dashboard if it
#     runs)
# The record store (/var/lib/sowgate), calibration files and /etc/sowgate are never touched.
set -eu

ROOT=""
ROLLBACK=0
while [ $# -gt 0 ]; do
    case "$1" in
        --root) ROOT=$(cd "$2" && pwd); shift 2 ;;
        --root=*) ROOT=$(cd "${1#--root=}" && pwd); shift ;;
        --rollback) ROLLBACK=1; shift ;;
        -h|--help) sed -n '2,29p' "$0"; exit 0 ;;
        *) echo "install.sh: unknown argument $1 (see --help)" >&2; exit 64 ;;
    esac
done

HERE=$(cd "$(dirname "$0")" && pwd)
# the bundle's wheels only, whatever pip configuration this box has
export PIP_CONFIG_FILE=/dev/null
unset PIP_INDEX_URL PIP_EXTRA_INDEX_URL PIP_FIND_LINKS PIP_CONSTRAINT PIP_REQUIRE_VIRTUALENV 2>/dev/null || true
OPT="$ROOT/opt/sowgate"
CONFIG=/etc/sowgate/sowgate.toml
DROPIN_DIR=/etc/systemd/system/sowgate.service.d
EX_CONFIG=78

say() { echo "install.sh: $*"; }
die() { echo "install.sh: $*" >&2; exit "${2:-1}"; }

# systemctl only on a box whose systemd runs (not with --root, not in a chroot/image build)
systemd_running() { [ -z "$ROOT" ] && [ -d /run/systemd/system ] && command -v systemctl >/dev/null; }

install_units() {
    share="$1"
    mkdir -p "$ROOT/etc/systemd/system" "$ROOT/etc/udev/rules.d" "$ROOT/etc/sowgate"
    cp "$share/systemd/sowgate.service" "$share/systemd/sowgate-dashboard.service" \
        "$ROOT/etc/systemd/system/"
    say "units installed in /etc/systemd/system (change them with drop-ins: systemctl edit sowgate)"
    if [ -e "$ROOT/etc/udev/rules.d/99-sowgate.rules" ]; then
        say "kept /etc/udev/rules.d/99-sowgate.rules (yours); this version's is in $share/udev"
    else
        cp "$share/udev/99-sowgate.rules" "$ROOT/etc/udev/rules.d/"
        say "installed /etc/udev/rules.d/99-sowgate.rules: put your adapters' serial numbers in it"
        if [ -z "$ROOT" ] && command -v udevadm >/dev/null && [ -d /run/udev ]; then
            udevadm control --reload && udevadm trigger --subsystem-match=tty || true
        fi
    fi
    if [ -e "$ROOT$CONFIG" ]; then
        say "kept $CONFIG"
    else
        install -m 0644 "$share/examples/sowgate.toml" "$ROOT$CONFIG"
        say "created $CONFIG from the example: edit it for this machine"
    fi
}

# check-config with the version now current; the service restarts only on a config it accepts
check_and_restart() {
    version="$1"
    if ! "$OPT/$version/bin/sowgate" check-config "$ROOT$CONFIG"; then
        die "$CONFIG does not pass sowgate $version's check-config (above): sowgate was NOT \
restarted. Fix it, then: sowgate check-config $CONFIG && systemctl restart sowgate" $EX_CONFIG
    fi
    # the unit's device classes narrowed to the ports this config names
    mkdir -p "$ROOT$DROPIN_DIR"
    if "$OPT/$version/bin/sowgate" check-config --systemd-device-allow "$ROOT$CONFIG" \
            > "$ROOT$DROPIN_DIR/devices.conf.new" 2>/dev/null; then
        mv "$ROOT$DROPIN_DIR/devices.conf.new" "$ROOT$DROPIN_DIR/devices.conf"
        say "$DROPIN_DIR/devices.conf: sowgate may open $(grep '^DeviceAllow=.' \
"$ROOT$DROPIN_DIR/devices.conf" | cut -d= -f2 | cut -d' ' -f1 | tr '\n' ' ')and no other device"
    else  # a version from before the option (a rollback): the drop-in there stays
        rm -f "$ROOT$DROPIN_DIR/devices.conf.new"
        say "WARNING: sowgate $version cannot write $DROPIN_DIR/devices.conf; \
$( [ -e "$ROOT$DROPIN_DIR/devices.conf" ] && echo "the one there is kept" || echo "the unit's device classes apply")" >&2
    fi
    if systemd_running; then
        systemctl daemon-reload
        systemctl enable --quiet sowgate.service
        systemctl restart sowgate.service
        systemctl try-restart sowgate-dashboard.service
        say "sowgate $version running: systemctl status sowgate"
    elif [ -z "$ROOT" ] && command -v systemctl >/dev/null; then
        systemctl enable --quiet sowgate.service  # works offline (image build, chroot)
        say "systemd is not running here: sowgate.service enabled, starts at the next boot"
    else
        say "sowgate $version installed in $OPT (no systemd here: nothing started)"
    fi
}

# point current (and /usr/bin/sowgate) at a version; the one it replaces becomes previous
switch_to() {
    version="$1"
    old=$(readlink "$OPT/current" 2>/dev/null || true)
    if [ -n "$old" ] && [ "$old" != "$version" ]; then
        ln -sfn "$old" "$OPT/previous"
    fi
    ln -sfn "$version" "$OPT/current.new" && mv -T "$OPT/current.new" "$OPT/current"
    mkdir -p "$ROOT/usr/bin"
    ln -sfn /opt/sowgate/current/bin/sowgate "$ROOT/usr/bin/sowgate"
    say "/opt/sowgate/current -> $version (previous: $(readlink "$OPT/previous" 2>/dev/null || echo none))"
}

if [ "$ROLLBACK" = 1 ]; then
    prev=$(readlink "$OPT/previous" 2>/dev/null || true)
    [ -n "$prev" ] && [ -x "$OPT/$prev/bin/sowgate" ] \
        || die "no previous version to go back to in $OPT"
    switch_to "$prev"
    install_units "$OPT/$prev/share"
    check_and_restart "$prev"
    exit 0
fi

# 1. this box
. "$HERE/BUNDLE"   # VERSION= ARCH=
[ "$(uname -m)" = "$ARCH" ] || die "this bundle is for $ARCH, this machine is $(uname -m): \
use sowgate-$VERSION-linux-$(uname -m).tar.gz"
command -v python3 >/dev/null || die "python3 is missing: apt install python3 python3-venv"
python3 -c 'import sys; sys.exit(sys.version_info < (3, 11))' \
    || die "python3 >= 3.11 is needed, this is $(python3 -V 2>&1) (Debian 12 / Raspberry Pi OS 12 have 3.11)"
python3 -c 'import ensurepip, venv' 2>/dev/null \
    || die "python3's venv module is missing: apt install python3-venv"
(cd "$HERE" && sha256sum --quiet --check SHA256SUMS) || die "the bundle is incomplete or damaged"

# 2. the virtualenv in /opt/sowgate/<version> (its scripts name that path, so it is built in
# place); a version already there (a reinstall) is moved aside and comes back if this fails
mkdir -p "$OPT"
FINAL="$OPT/$VERSION"
OLD="$OPT/.$VERSION.old"
rm -rf "$OLD"
[ -e "$FINAL" ] && mv "$FINAL" "$OLD"
failed() {
    rm -rf "$FINAL"
    [ -e "$OLD" ] && mv "$OLD" "$FINAL"
    die "$1"
}
say "installing sowgate $VERSION into /opt/sowgate/$VERSION from the bundle's wheels (offline)"
python3 -m venv "$FINAL" || failed "python3 -m venv failed (apt install python3-venv)"
# An upgrade starts from a copy of the running version's packages: pip then installs only what
# this bundle pins differently (sowgate itself at least) instead of all ~50 wheels again, which
# takes minutes on a Raspberry Pi. Only for the same python (the site-packages path matches).
run=$(readlink "$OPT/current" 2>/dev/null || true)
if [ -n "$run" ] && [ "$run" != "$VERSION" ]; then
    for site in "$OPT/$run"/lib/python3*/site-packages; do
        new_site="$FINAL/lib/$(basename "$(dirname "$site")")/site-packages"
        if [ -d "$site" ] && [ -d "$new_site" ]; then
            cp -a "$site/." "$new_site/" || failed "could not copy $run's packages"
            say "started from $run's packages; pip installs what this bundle pins differently"
        fi
    done
fi
"$FINAL/bin/python" -m pip install --quiet --no-index --disable-pip-version-check \
    --find-links "$HERE/wheels" --constraint "$HERE/constraints.txt" "sowgate==$VERSION" \
    || failed "pip could not install the bundle's wheels (above); nothing was changed"
"$FINAL/bin/sowgate" --version >/dev/null || failed "the installed sowgate does not run"
rm -rf "$OLD"

# 3. what this version shipped, for --rollback and for reference
mkdir -p "$FINAL/share"
cp -r "$HERE/systemd" "$HERE/udev" "$HERE/examples" "$HERE/BUNDLE" "$FINAL/share/"

# 4. links; keep current and previous only
switch_to "$VERSION"
keep_prev=$(readlink "$OPT/previous" 2>/dev/null || true)
for dir in "$OPT"/*/; do
    name=$(basename "$dir")
    case "$name" in current|previous|"$VERSION"|"$keep_prev") ;; *)
        [ -L "${dir%/}" ] || { rm -rf "${dir%/}"; say "removed old version $name"; } ;;
    esac
done

# 5.-9.
install_units "$FINAL/share"
check_and_restart "$VERSION"
