"""Make sure a libLLVM >= 16 exists for Dr.Jit's CPU backend (run by `make install`).

If none is found and we run as root on a Debian/Ubuntu machine, install Debian's
``libllvm19`` with apt; otherwise print the one command that fixes it and fail.
"""
import os
import shutil
import subprocess
import sys

from sonarsim import runtime


def main() -> int:
    path = runtime.configure_llvm()
    if path:
        print(f"libLLVM ok: {path}")
        return 0
    fix = "sudo apt-get update && sudo apt-get install -y libllvm19"
    if os.geteuid() == 0 and shutil.which("apt-get"):
        print("no libLLVM >= 16 found; installing Debian's libllvm19 ...", flush=True)
        env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
        ok = subprocess.run(["apt-get", "install", "-y", "-q", "libllvm19"], env=env).returncode == 0
        if not ok:  # package lists may be missing on a fresh machine
            ok = (subprocess.run(["apt-get", "update", "-q"], env=env).returncode == 0 and
                  subprocess.run(["apt-get", "install", "-y", "-q", "libllvm19"],
                                 env=env).returncode == 0)
        path = runtime.configure_llvm() if ok else None
        if path:
            print(f"libLLVM ok: {path}")
            return 0
    print(f"error: no libLLVM >= 16 for Dr.Jit's CPU backend; fix: {fix}", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
