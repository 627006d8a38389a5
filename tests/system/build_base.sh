#!/bin/sh
# The cached part of the system test's guest: a Debian 12 root (debootstrap, ~2 min, once) and
# Debian's own kernel with a busybox initrd that loads what the root needs (virtio disk, ext4,
# 9p for the results share, vcan). Everything under $1 (build/system-test); rerun is a no-op.
set -eu
OUT=$(realpath -m "${1:-build/system-test}")
MIRROR=${MIRROR:-http://deb.debian.org/debian}
mkdir -p "$OUT"

if [ ! -e "$OUT/base.done" ]; then
    rm -rf "$OUT/base"
    debootstrap --variant=minbase \
        --include=systemd,systemd-sysv,dbus,udev,kmod,iproute2,python3,python3-venv,mosquitto,sqlite3 \
        bookworm "$OUT/base" "$MIRROR" > "$OUT/debootstrap.log" 2>&1 \
        || { tail -20 "$OUT/debootstrap.log" >&2; exit 1; }
    rm -rf "$OUT/base/var/cache/apt/archives/"*.deb
    touch "$OUT/base.done"
fi

if [ ! -e "$OUT/kernel.done" ]; then
    rm -rf "$OUT/kernel" "$OUT/initrd"
    mkdir -p "$OUT/kernel" "$OUT/initrd/bin" "$OUT/initrd/lib/modules"
    pkg=$(apt-cache depends linux-image-amd64 | sed -n 's/.*Depends: \(linux-image-[0-9].*-amd64\)$/\1/p' | head -1)
    (cd "$OUT/kernel" && apt-get download -qq -o APT::Sandbox::User=root "$pkg" && dpkg-deb -x ./*.deb . && rm ./*.deb)
    kv=$(ls "$OUT/kernel/lib/modules")
    depmod -b "$OUT/kernel" "$kv"
    cp "$OUT/kernel/boot/vmlinuz-$kv" "$OUT/vmlinuz"
    cp /bin/busybox "$OUT/initrd/bin/busybox"
    for m in virtio_pci virtio_blk ext4 9p 9pnet_virtio can_raw vcan; do
        modprobe -d "$OUT/kernel" -S "$kv" --show-depends "$m" | awk '$1 == "insmod" {print $2}'
    done | awk '!seen[$0]++' > "$OUT/initrd/modules.order"
    while read -r ko; do cp "$ko" "$OUT/initrd/lib/modules/"; done < "$OUT/initrd/modules.order"
    sed -i 's|.*/||' "$OUT/initrd/modules.order"
    cat > "$OUT/initrd/init" <<'INIT'
#!/bin/busybox sh
/bin/busybox --install -s /bin
mount -t proc proc /proc; mount -t sysfs sys /sys; mount -t devtmpfs dev /dev
for m in $(cat /modules.order); do insmod /lib/modules/$m 2>/dev/null; done
for i in 1 2 3 4 5 6 7 8 9 10; do [ -b /dev/vda ] && break; sleep 0.2; done
mkdir -p /root && mount -t ext4 -o rw /dev/vda /root || { echo "initrd: no /dev/vda"; sh; }
umount /proc /sys; mount --move /dev /root/dev 2>/dev/null || umount /dev
exec switch_root /root /sbin/init
INIT
    chmod +x "$OUT/initrd/init"
    mkdir -p "$OUT/initrd/proc" "$OUT/initrd/sys" "$OUT/initrd/dev" "$OUT/initrd/root"
    (cd "$OUT/initrd" && find . | busybox cpio -o -H newc 2>/dev/null | gzip -1) > "$OUT/initrd.img"
    touch "$OUT/kernel.done"
fi
