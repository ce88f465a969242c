"""Point Dr.Jit's LLVM backend at libLLVM 19 unless the user chose one.

Dr.Jit needs libLLVM >= 15, but 15 and 16 abort inside ``mi.render``; the
Debian package ``libllvm19`` works. This must run before the LLVM backend
starts, i.e. before the first LLVM variant is set: the package's
``__init__`` calls it first, so every module of mi-amr runs after it.
"""

import glob
import os

_CANDIDATES = ("/usr/lib/*/libLLVM.so.19*", "/usr/lib/*/libLLVM-19.so",
               "/usr/lib/llvm-19/lib/libLLVM*.so*")


def find_llvm19():
    for pattern in _CANDIDATES:
        hits = sorted(glob.glob(pattern))
        if hits:
            return hits[0]
    return None


def ensure_llvm_path():
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        path = find_llvm19()
        if path:
            os.environ["DRJIT_LIBLLVM_PATH"] = path
