#!/usr/bin/env bash
# Install what mcrecon's Mitsuba 3 bridge (mcrecon/renderers/mitsuba.py) needs on a
# Debian machine with Python 3.11:
#   * the Debian package libllvm19: Dr.Jit's LLVM backend (the llvm_ad_rgb
#     variant) loads libLLVM at run time; with LLVM 15/16 the first render
#     aborts the whole process, so an older libLLVM is not good enough;
#   * the PyPI package mitsuba (pulls in drjit).
#
# Idempotent: each step is skipped when already done.  It never fails the
# caller: when a step is impossible (no apt, not root, no network, no
# package), it prints the reason and exits 0, and the Mitsuba tests then skip
# with a visible reason (mcrecon.renderers.mitsuba.mitsuba_available()).
#
# Usage: bash data_tools/install_mitsuba.sh   (PYTHON=... to choose the interpreter)
set -u

PYTHON="${PYTHON:-python}"
say() { echo "install_mitsuba: $*"; }

have_libllvm19() {
    # ldconfig knows the library once the package is installed.
    ldconfig -p 2>/dev/null | grep -q 'libLLVM\(-19\|\.so\.19\)' && return 0
    dpkg-query -W -f='${Status}' libllvm19 2>/dev/null | grep -q "install ok installed"
}

# ---------------------------------------------------------------- libllvm19
if have_libllvm19; then
    say "libllvm19 already installed"
elif ! command -v apt-get >/dev/null 2>&1; then
    say "SKIP libllvm19: apt-get not found (not a Debian machine); the llvm variant will not load"
elif [ "$(id -u)" != "0" ]; then
    say "SKIP libllvm19: not root, cannot run apt-get install; the llvm variant will not load"
else
    export DEBIAN_FRONTEND=noninteractive
    # 'apt-get update' only when the package lists do not know libllvm19 yet.
    if ! apt-cache show libllvm19 >/dev/null 2>&1; then
        say "apt-get update"
        apt-get update -qq >/dev/null 2>&1 || say "apt-get update failed (network?)"
    fi
    if apt-cache show libllvm19 >/dev/null 2>&1; then
        say "apt-get install -y libllvm19"
        if apt-get install -y -qq --no-install-recommends libllvm19 >/dev/null 2>&1; then
            say "libllvm19 installed"
        else
            say "SKIP libllvm19: apt-get install failed; the llvm variant will not load"
        fi
    else
        say "SKIP libllvm19: the package lists do not offer libllvm19; the llvm variant will not load"
    fi
fi

# ------------------------------------------------------------------ mitsuba
if ! command -v "$PYTHON" >/dev/null 2>&1; then
    say "SKIP mitsuba: no Python interpreter '$PYTHON'"
elif "$PYTHON" -c "import mitsuba, drjit" >/dev/null 2>&1; then
    say "mitsuba already installed: $("$PYTHON" -c 'import mitsuba; print(mitsuba.__version__)' 2>/dev/null)"
else
    say "pip install mitsuba"
    if "$PYTHON" -m pip install -q --disable-pip-version-check "mitsuba>=3.5" 2>&1 | tail -n 3; then :; fi
    if "$PYTHON" -c "import mitsuba, drjit" >/dev/null 2>&1; then
        say "mitsuba installed: $("$PYTHON" -c 'import mitsuba; print(mitsuba.__version__)' 2>/dev/null)"
    else
        say "SKIP mitsuba: pip install failed; the Mitsuba tests will skip"
    fi
fi

# ------------------------------------------------------------------- probe
# Report (never fail) whether the bridge can actually render, using the same
# subprocess probe the tests use, when mcrecon is importable.
if "$PYTHON" -c "import mcrecon.renderers.mitsuba" >/dev/null 2>&1; then
    "$PYTHON" - <<'PY' || true
from mcrecon.renderers.mitsuba import mitsuba_available
ok, reason = mitsuba_available(refresh=True)
print("install_mitsuba: bridge", "available" if ok else "NOT available", "-", reason)
PY
fi
exit 0
