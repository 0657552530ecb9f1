#!/usr/bin/env bash
# Build (once) the guest assets that scripts/vmrun boots, into DIR/BACKEND/.
#
#   build-assets.sh ensure BACKEND DIR   # build if missing or stale; fast no-op otherwise
#   build-assets.sh build  BACKEND DIR   # rebuild unconditionally
#
# BACKEND uml:  /usr/bin/linux.uml (package user-mode-linux) + an initramfs with busybox,
#               the init script and the CAN/overlay modules from /usr/lib/uml/modules.
# BACKEND qemu: vmlinux unpacked from the stock Debian kernel (linux-image-amd64, or
#               KPKG=linux-image-X-amd64) + an initramfs with virtio/9p/overlay/CAN modules.
# Output: DIR/BACKEND/{initramfs.cpio.gz,kernel.release[,vmlinux]} and a stamp. The stamp
# holds a key over the inputs, so that editing init or this script rebuilds.
set -euo pipefail

HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
ACTION=${1:?usage: build-assets.sh ensure|build BACKEND DIR}
BACKEND=${2:?backend}
DIR=${3:?dir}
OUT=$DIR/$BACKEND

log() { echo "vmrun-assets: $*" >&2; }
die() { echo "vmrun-assets: error: $*" >&2; exit 1; }

UML_BIN=/usr/bin/linux.uml
BUSYBOX=/bin/busybox

# Protocols are preloaded because the guest cannot autoload modules; can-isotp exists only
# in the Debian kernel (UML's config lacks it).
CAN_MODS="can can-raw can-bcm can-gw can-j1939 can-dev vcan vxcan"
UML_MODS="overlay $CAN_MODS"
QEMU_MODS="virtio_pci virtio_mmio 9pnet_virtio 9p overlay virtio_console $CAN_MODS can-isotp"

# Key over everything the assets depend on; cheap enough (stat + md5 of two small files)
# to compute on every vmrun.
stamp_key() {
    local k
    k=$(cat "$HERE/init" "$HERE/build-assets.sh" | md5sum | cut -c1-32)
    case $BACKEND in
        uml) k="$k $(stat -L -c %s:%Y $UML_BIN $BUSYBOX 2>/dev/null | tr '\n' ' ')" ;;
        qemu) k="$k ${KPKG:-linux-image-amd64} $(stat -L -c %s:%Y $BUSYBOX 2>/dev/null)" ;;
        *) die "unknown backend '$BACKEND' (uml or qemu)" ;;
    esac
    echo "$k"
}

KEY=$(stamp_key)
if [ "$ACTION" = ensure ] && [ "$(cat "$OUT/stamp" 2>/dev/null)" = "$KEY" ]; then
    exit 0
fi

mkdir -p "$DIR"
# Concurrent vmruns on a fresh tree: one builds, the others wait and then reuse.
exec 9>"$DIR/.lock"
flock 9
if [ "$ACTION" = ensure ] && [ "$(cat "$OUT/stamp" 2>/dev/null)" = "$KEY" ]; then
    exit 0
fi

if ! command -v cpio >/dev/null || ! command -v modprobe >/dev/null || [ ! -x $BUSYBOX ]; then
    die "missing tools: run VMRUN_BACKEND=$BACKEND scripts/install-test-deps.sh"
fi

T=$(mktemp -d "$DIR/.build.XXXXXX")
trap 'rm -rf "$T"' EXIT
log "building $BACKEND guest assets in $OUT"
started=$SECONDS

# modroot KREL MODDIR: a tree that depmod/modprobe accept (ROOT/lib/modules/KREL).
mkdir -p "$T/modroot/lib/modules" "$T/initramfs"
case $BACKEND in
uml)
    [ -x $UML_BIN ] || die "$UML_BIN missing: run scripts/install-test-deps.sh"
    KREL=$(find /usr/lib/uml/modules -mindepth 1 -maxdepth 1 -printf '%f\n' | sort -V | tail -n1)
    [ -n "$KREL" ] || die "no /usr/lib/uml/modules/<release>"
    # The package ships modules.dep, so no depmod is needed.
    ln -s "/usr/lib/uml/modules/$KREL" "$T/modroot/lib/modules/$KREL"
    MODS=$UML_MODS
    ;;
qemu)
    if ! command -v qemu-system-x86_64 >/dev/null || ! command -v xz >/dev/null; then
        die "qemu missing: run VMRUN_BACKEND=qemu scripts/install-test-deps.sh"
    fi
    KPKG=${KPKG:-$(apt-cache depends linux-image-amd64 2>/dev/null |
        sed -n 's/^ *Depends: \(linux-image-[0-9].*-amd64\)$/\1/p' | awk 'NR == 1')}
    [ -n "$KPKG" ] || die "cannot resolve linux-image-amd64 (apt-get update needed?)"
    log "downloading $KPKG"
    # Not installed on the host: only unpacked here. (The cloud flavour lacks CAN and 9p.)
    (cd "$T" && apt-get download -q "$KPKG" >/dev/null 2>"$T/dl.log") ||
        { cat "$T/dl.log" >&2; die "apt-get download $KPKG failed"; }
    dpkg -x "$T"/"$KPKG"_*.deb "$T/kroot"
    KREL=$(ls "$T/kroot/lib/modules")
    mv "$T/kroot/lib/modules/$KREL" "$T/modroot/lib/modules/$KREL"
    depmod -b "$T/modroot" "$KREL"   # the .deb has no modules.dep (made at install time)
    # bzImage costs ~3.5 s of xz under TCG on every boot: unpack the ELF vmlinux once;
    # QEMU boots it through its PVH entry.
    off=$(LC_ALL=C grep -obUaP '\xfd7zXZ\x00' "$T/kroot/boot/vmlinuz-$KREL" | awk -F: 'NR == 1 { print $1 }')
    [ -n "$off" ] || die "no xz payload in vmlinuz-$KREL"
    # (xz stops at the end of its stream, so tail gets SIGPIPE: check the result instead.)
    { tail -c +$((off + 1)) "$T/kroot/boot/vmlinuz-$KREL" || true; } | xz -dc --single-stream >"$T/vmlinux"
    [ "$(head -c 4 "$T/vmlinux" | od -An -c | tr -d ' ')" = 177ELF ] || die "vmlinux extraction failed"
    MODS=$QEMU_MODS
    ;;
esac

# Module load order, each module once, from modprobe's own resolution.
mkdir -p "$T/initramfs/lib/modules"
: >"$T/initramfs/modules.order"
for m in $MODS; do
    modprobe -d "$T/modroot" -S "$KREL" --show-depends "$m" ||
        die "module $m not found for $KREL"
done | awk '$1 == "insmod" && !seen[$2]++ { print $2 }' | while read -r ko; do
    case $ko in *.ko) ;; *) die "compressed module $ko: busybox insmod needs plain .ko" ;; esac
    name=$(basename "$ko" .ko)
    cp "$ko" "$T/initramfs/lib/modules/$name.ko"
    echo "$name" >>"$T/initramfs/modules.order"
done

# Initramfs: static busybox (no libc in there) with its applets as links, and /init.
R=$T/initramfs
mkdir -p "$R/bin" "$R/proc" "$R/sys" "$R/dev" "$R/tmp"
cp $BUSYBOX "$R/bin/busybox"
for a in $($BUSYBOX --list); do [ "$a" = busybox ] || ln -s busybox "$R/bin/$a"; done
install -m 0755 "$HERE/init" "$R/init"
(cd "$R" && find . | LC_ALL=C sort | cpio -o -H newc --quiet -R 0:0 | gzip -1) >"$T/initramfs.cpio.gz"

# Publish: replace OUT as a whole, then write the stamp last.
mkdir -p "$T/out"
mv "$T/initramfs.cpio.gz" "$T/out/"
[ -f "$T/vmlinux" ] && mv "$T/vmlinux" "$T/out/"
echo "$KREL" >"$T/out/kernel.release"
cp "$T/initramfs/modules.order" "$T/out/"
rm -rf "$OUT"
mv "$T/out" "$OUT"
echo "$KEY" >"$OUT/stamp"
log "done in $((SECONDS - started)) s (kernel $KREL)"
