"""The native module (dr_native.mpy) for the board's instruction set: the MicroPython source tree it is built
against (sources), the compiler routes (xtensa_llvm for ESP32 boards without xtensa-esp32-elf-gcc), the build
(build), and the checks that it is what the linker meant (mpyfile reads a .mpy, verify decodes its relocated
instructions against the link map, abi compares it with the firmware release the board declares).
"""
