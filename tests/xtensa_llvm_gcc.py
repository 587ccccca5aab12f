#!/usr/bin/env python3
"""Stands in for xtensa-esp32-elf-gcc (which no registry ships) in MicroPython's natmod build: `-c SRC -o OBJ` runs
clang-22 (Xtensa target, freestanding, clang's and picolibc's headers) to LLVM IR, then llc-22 -mcpu=esp32 to an
object. Used by tests/test_kernel_natmod.py as `make ARCH=xtensawin CROSS=<folder>/xtensa-llvm-`."""
import subprocess
import sys


def main(args):
    out = args[args.index("-o") + 1]
    source = args[args.index("-c") + 1]
    keep = [a for a in args if a.startswith(("-I", "-D", "-std", "-O"))]
    resource = subprocess.run(["clang-22", "-print-resource-dir"], capture_output=True, text=True).stdout.strip()
    ir = out + ".ll"
    subprocess.run(["clang-22", "--target=xtensa", "-ffreestanding", "-nostdinc", "-isystem", resource + "/include",
                    "-isystem", "/usr/lib/picolibc/arm-none-eabi/include", *keep, "-Wno-typedef-redefinition",
                    "-S", "-emit-llvm", source, "-o", ir], check=True)
    # -function-sections: llc otherwise stops at "fixup value must be 4-byte aligned"
    subprocess.run(["llc-22", "-mtriple=xtensa", "-mcpu=esp32", "-O2", "-function-sections", "-filetype=obj", ir,
                    "-o", out], check=True)


if __name__ == "__main__":
    main(sys.argv[1:])
