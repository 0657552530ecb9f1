#!/usr/bin/env bash
# Install what the test tiers need on a Debian (bookworm) machine, as root.
#
#   scripts/install-test-deps.sh [--python] [--qemu]
#
#   --python  (or TEST_DEPS_PYTHON=1): also make build/venv with python-can, canopen, pymodbus,
#             asyncua (the python peers of the CANopen, Modbus and OPC UA tests)
#   --qemu    (or VMRUN_BACKEND=qemu): also install the QEMU fallback backend of scripts/vmrun
#
# Idempotent: every step checks first, and `apt-get update` runs only when something
# must be installed, so a second run costs next to nothing (CI runs it every time).
set -euo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
WANT_PYTHON=${TEST_DEPS_PYTHON:-0}
WANT_QEMU=0
[ "${VMRUN_BACKEND:-uml}" = qemu ] && WANT_QEMU=1
# A host with AMX cannot run User-Mode Linux 6.1 (scripts/vmrun): the QEMU backend is its default.
[ -z "${VMRUN_BACKEND:-}" ] && grep -qw amx_tile /proc/cpuinfo 2>/dev/null && WANT_QEMU=1
for a in "$@"; do
    case $a in
        --python) WANT_PYTHON=1 ;;
        --qemu) WANT_QEMU=1 ;;
        -h|--help) awk 'NR > 1 && !/^#/ { exit } NR > 1 && !/shellcheck/ { sub(/^# ?/, ""); print }' "$0"; exit 0 ;;
        *) echo "install-test-deps: unknown argument: $a" >&2; exit 2 ;;
    esac
done

export DEBIAN_FRONTEND=noninteractive
SUDO=
if [ "$(id -u)" != 0 ]; then
    command -v sudo >/dev/null || { echo "install-test-deps: need root (or sudo)" >&2; exit 1; }
    SUDO="sudo -n"
fi

log() { echo "install-test-deps: $*" >&2; }

# Debian packages to install later in one apt-get call.
MISSING=()
need_pkg() {   # need_pkg PACKAGE...: queue each package that dpkg does not list as installed
    local p
    for p in "$@"; do
        dpkg-query -W -f='${db:Status-Abbrev}' "$p" 2>/dev/null | grep -q '^ii' || MISSING+=("$p")
    done
}

APT_UPDATED=0
apt_update_once() {
    [ "$APT_UPDATED" = 1 ] && return 0
    log "apt-get update"
    $SUDO apt-get update -qq
    APT_UPDATED=1
}

install_missing() {
    [ ${#MISSING[@]} -eq 0 ] && return 0
    apt_update_once
    log "installing: ${MISSING[*]}"
    $SUDO apt-get install -y -qq --no-install-recommends "${MISSING[@]}" >/dev/null
    MISSING=()
}

# --- vcan tier: guest kernel and the tools that build its initramfs (scripts/vm/) ---
vcan_tier_deps() {
    # user-mode-linux: the guest kernel (+ its CAN modules) as a plain host process.
    # busybox-static: the initramfs userland (no libc in there). kmod: depmod/modprobe
    # to resolve module order. cpio+gzip: pack the initramfs. iproute2: `ip` for the
    # native vcan path. util-linux: setsid/flock (essential, listed for clarity).
    need_pkg user-mode-linux busybox-static kmod cpio gzip iproute2 util-linux
    if [ "$WANT_QEMU" = 1 ]; then
        # The QEMU fallback boots the stock Debian kernel, fetched by the asset builder
        # with `apt-get download`; xz-utils unpacks vmlinux from the bzImage.
        need_pkg qemu-system-x86 xz-utils
    fi
    install_missing
    if [ "$WANT_QEMU" = 1 ] && ! apt-cache show linux-image-amd64 >/dev/null 2>&1; then
        apt_update_once   # package lists are needed for `apt-get download` of the kernel
    fi
}

# --- other test prerequisites: add new ones here -------------------------------------
extra_test_deps() {
    # Modbus peers we did not write (sim-drives/tests/modbus_tools.rs): socat makes the
    # pseudo-terminal pair an RTU line runs over; mbpoll is a Modbus RTU/TCP master.
    need_pkg socat mbpoll
    # tmux: the interactive `cncgw run` is typed at and read back in a terminal
    # (tests/realtime/cli_tmux.rs: send-keys, capture-pane).
    need_pkg tmux
    # man-db (man -l) and groff: every manual page `cncgw man --dir` writes is rendered
    # (tests/cli/cli_man.rs).
    need_pkg man-db groff-base
    # librsvg2-bin (rsvg-convert): the pictures are rendered to PNG in their tests
    # (tests/cli/svg_common.rs) and `-o FILE.png` goes through it.
    need_pkg librsvg2-bin
    # systemd (systemd-sysusers, systemd-tmpfiles, systemd-analyze): the deploy files are
    # installed into a scratch root and verified (tests/cli/deploy.rs).
    need_pkg systemd
    install_missing
    if [ "$WANT_PYTHON" = 1 ]; then
        python_venv
    fi
}

# Python peers for the protocol tests (a CANopen/Modbus implementation written elsewhere).
# Uses Debian's /usr/bin/python3, not a pyenv shim (slow under the guest, see notes).
# Floors: the versions the socketcand peer test (tests/python/) was written against.
# asyncua: the OPC UA client of tests/cli/opcua_server.rs.
PY_REQS=("python-can>=4.6" "canopen>=2.4" pymodbus "asyncua>=1.1")
python_venv() {
    local venv=$ROOT/build/venv
    if [ -x "$venv/bin/python" ] && [ "$(cat "$venv/.installed" 2>/dev/null)" = "${PY_REQS[*]}" ]; then
        return 0
    fi
    need_pkg python3 python3-venv
    install_missing
    log "making $venv with: ${PY_REQS[*]}"
    /usr/bin/python3 -m venv "$venv"
    "$venv/bin/pip" install -q --disable-pip-version-check "${PY_REQS[@]}"
    echo "${PY_REQS[*]}" >"$venv/.installed"
}

# --- fuzzing: cargo-fuzz (scripts/fuzz.sh; scripts/test.sh runs each target briefly) ---
# The targets build on the stable toolchain (`cargo fuzz build -s none`: coverage
# instrumentation only), so no nightly toolchain is needed. libfuzzer-sys compiles libFuzzer
# (C++): g++. Installed for the invoking user (not root), like the rest of the toolchain.
CARGO_FUZZ_VERSION=0.13.2
fuzz_deps() {
    need_pkg g++
    install_missing
    if ! cargo fuzz --version >/dev/null 2>&1; then
        command -v cargo >/dev/null || { log "cargo not found: install Rust (rustup) first"; exit 1; }
        log "cargo install cargo-fuzz $CARGO_FUZZ_VERSION"
        cargo install --locked --quiet cargo-fuzz --version "$CARGO_FUZZ_VERSION"
        cargo fuzz --version >/dev/null || { log "cargo-fuzz did not install"; exit 1; }
    fi
}

vcan_tier_deps
extra_test_deps
fuzz_deps
log "ok"
