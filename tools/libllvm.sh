#!/bin/sh
# Print the path of a shared libLLVM of version 16 or newer, which Dr.Jit's LLVM backend needs
# (versions 14 and 15 crash while compiling Mitsuba's kernels). On Debian/Ubuntu as root, install
# the distribution's libllvm19 when none is found. Exit non-zero with a message otherwise.
set -eu

find_llvm() {
    # An explicit choice wins when it points at a file.
    if [ -n "${DRJIT_LIBLLVM_PATH:-}" ] && [ -f "${DRJIT_LIBLLVM_PATH}" ]; then
        echo "${DRJIT_LIBLLVM_PATH}"
        return 0
    fi
    command -v ldconfig >/dev/null 2>&1 || [ -x /sbin/ldconfig ] || return 1
    LDC=$(command -v ldconfig 2>/dev/null || echo /sbin/ldconfig)
    # Lines look like: "libLLVM.so.19.1 (libc6,x86-64) => /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
    # or "libLLVM-17.so.1 (...) => ...". Pick the newest major version >= 16.
    "$LDC" -p 2>/dev/null | awk '
        /libLLVM[-.]/ {
            name = $1; path = $NF
            v = name; sub(/^libLLVM[-.](so\.)?/, "", v); sub(/[^0-9].*$/, "", v)
            if (v + 0 >= 16 && v + 0 > best) { best = v + 0; bestpath = path }
        }
        END { if (best) print bestpath; else exit 1 }'
}

if path=$(find_llvm); then
    echo "$path"
    exit 0
fi

if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
    echo "libllvm.sh: no libLLVM >= 16 found; installing Debian's libllvm19" >&2
    # Wait up to 5 minutes for a package manager already at work (unattended upgrades on a
    # fresh machine hold dpkg's lock) instead of failing at once.
    APT="apt-get -o DPkg::Lock::Timeout=300"
    if ! $APT install -y -q libllvm19 >&2; then
        $APT update -q >&2 && $APT install -y -q libllvm19 >&2 || true
    fi
    if path=$(find_llvm); then
        echo "$path"
        exit 0
    fi
fi

cat >&2 <<'MSG'
error: Dr.Jit's LLVM backend needs a shared libLLVM of version 16 or newer, and none was found.
  Debian/Ubuntu: sudo apt-get install libllvm19
  Fedora:        sudo dnf install llvm-libs
  macOS:         brew install llvm
Then set DRJIT_LIBLLVM_PATH to the library file (libLLVM.so.NN / libLLVM.dylib) and run again.
MSG
exit 1
