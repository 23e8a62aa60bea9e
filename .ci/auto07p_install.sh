#!/usr/bin/env bash
# Install AUTO-07p (Debian package auto-07p: prebuilt AUTO-07p 0.9.2 library objects in
# /usr/lib/auto-07p) plus gfortran, which the package does not depend on but which is needed
# to build every AUTO equations file.  Used by tests/auto07p_reference.py.
# Idempotent and quiet; always exits 0 (the AUTO tests skip, with the reason, without it).
cd "$(dirname "$0")/.." || exit 0

have_auto() {
    ls /usr/lib/auto-07p/lib/*.o >/dev/null 2>&1 && command -v gfortran >/dev/null 2>&1
}
if have_auto; then
    exit 0
fi

SUDO=""
if [ "$(id -u)" != "0" ]; then
    if command -v sudo >/dev/null 2>&1; then
        SUDO="sudo -n"
    else
        echo "auto07p_install: not root and no sudo; AUTO-07p not installed (tests will skip)" >&2
        exit 0
    fi
fi
if ! command -v apt-get >/dev/null 2>&1; then
    echo "auto07p_install: no apt-get (not Debian/Ubuntu); AUTO-07p not installed (tests will skip)" >&2
    exit 0
fi

export DEBIAN_FRONTEND=noninteractive
log=$(mktemp)
if ! $SUDO apt-get install -y -qq auto-07p gfortran >"$log" 2>&1; then
    # stale or missing package lists: refresh once and retry
    $SUDO apt-get update -qq >>"$log" 2>&1
    if ! $SUDO apt-get install -y -qq auto-07p gfortran >>"$log" 2>&1; then
        echo "auto07p_install: apt-get install auto-07p gfortran failed (tests will skip):" >&2
        tail -n 5 "$log" >&2
    fi
fi
rm -f "$log"
if ! have_auto; then
    echo "auto07p_install: AUTO-07p still unavailable after install attempt (tests will skip)" >&2
fi
exit 0
