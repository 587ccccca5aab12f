# Bare-metal start for qemu-system-xtensa -M sim -cpu de233_fpu (windowed registers, 32 physical address registers,
# FPU as coprocessor 0), loaded at the reset VECBASE (0x2000) by codegen.natmod.qemu_xtensa; no relocations.
#   0x2000 + 0x000..0x140  window overflow/underflow handlers (the ABI's spill convention: a call's a0-a3 in the
#                          16 bytes below the sp of the call it made, its a4-a11 below its caller's sp)
#   0x2000 + 0x300, 0x3c0  kernel and double exception: MOVSP's AllocaCause is handled (the caller's registers
#                          restored), any other stops with exit status 64 + EXCCAUSE
#   0x2400                 _start: windows, PS, FPU, instruction counter, stack; call8 the harness at HARNESS
#                          with the input block's address; semihosting write(1, OUTPUT, bytes it returned); exit 0
# SIMCALL (0x005100) is written as bytes: llvm-mc does not know the mnemonic.
	.text
	.org 0x000
_WindowOverflow4:
	s32e a0, a5, -16
	s32e a1, a5, -12
	s32e a2, a5, -8
	s32e a3, a5, -4
	rfwo
	.org 0x040
_WindowUnderflow4:
	l32e a0, a5, -16
	l32e a1, a5, -12
	l32e a2, a5, -8
	l32e a3, a5, -4
	rfwu
	.org 0x080
_WindowOverflow8:
	s32e a0, a9, -16
	l32e a0, a1, -12
	s32e a1, a9, -12
	s32e a2, a9, -8
	s32e a3, a9, -4
	s32e a4, a0, -32
	s32e a5, a0, -28
	s32e a6, a0, -24
	s32e a7, a0, -20
	rfwo
	.org 0x0c0
_WindowUnderflow8:
	l32e a1, a9, -12
	l32e a0, a9, -16
	l32e a7, a1, -12
	l32e a2, a9, -8
	l32e a4, a7, -32
	l32e a3, a9, -4
	l32e a5, a7, -28
	l32e a6, a7, -24
	l32e a7, a7, -20
	rfwu
	.org 0x100
_WindowOverflow12:
	s32e a0, a13, -16
	l32e a0, a1, -12
	s32e a1, a13, -12
	s32e a2, a13, -8
	s32e a3, a13, -4
	s32e a4, a0, -48
	s32e a5, a0, -44
	s32e a6, a0, -40
	s32e a7, a0, -36
	s32e a8, a0, -32
	s32e a9, a0, -28
	s32e a10, a0, -24
	s32e a11, a0, -20
	rfwo
	.org 0x140
_WindowUnderflow12:
	l32e a1, a13, -12
	l32e a0, a13, -16
	l32e a11, a1, -12
	l32e a2, a13, -8
	l32e a4, a11, -48
	l32e a8, a11, -32
	l32e a3, a13, -4
	l32e a5, a11, -44
	l32e a6, a11, -40
	l32e a7, a11, -36
	l32e a9, a11, -28
	l32e a10, a11, -24
	l32e a11, a11, -20
	rfwu
	.org 0x300
_KernelException:
	wsr a0, excsave1
	rsr a0, exccause
	beqi a0, 5, _Alloca
	rsr a3, exccause
	addi a3, a3, 64
	movi a2, 1
	.byte 0x00, 0x51, 0x00     # exit(64 + EXCCAUSE)
# MOVSP found its caller's registers spilled (AllocaCause): bring them back as the return to the caller would
# (the underflow handler of the caller's call size), then RFWU re-runs the MOVSP. PS.OWB is set to the frame that
# raised the exception, so RFWU returns to it.
_Alloca:
	rsr a0, windowbase
	rotw -1                    # the raising frame's a0..a7 are now a4..a11; a0..a3 are free
	rsr a2, ps
	extui a3, a2, 8, 4
	xor a3, a3, a4
	slli a3, a3, 8
	xor a2, a2, a3
	wsr a2, ps                 # PS.OWB = the raising frame's window base
	rsync
	rsr a4, excsave1           # its a0: the return address, call size in bits 31..30
	bbci a4, 31, _Alloca4
	rotw -1
	bbci a8, 30, _Alloca8
	rotw -1
	j _WindowUnderflow12
_Alloca4:
	j _WindowUnderflow4
_Alloca8:
	j _WindowUnderflow8
	.org 0x3c0
_DoubleException:
	movi a3, 127
	movi a2, 1
	.byte 0x00, 0x51, 0x00
	.org 0x400
_start:
	movi a2, 1
	wsr a2, windowstart
	movi a2, 0
	wsr a2, windowbase
	rsync
	movi a2, 4
	slli a2, a2, 16
	wsr a2, ps                 # WOE, ring 0, interrupt level 0, no EXCM
	movi a2, 1
	wsr a2, cpenable           # the FPU
	wsr a2, icountlevel        # ICOUNT counts every instruction at interrupt level 0
	movi a2, 0
	wsr a2, icount
	rsync
	movi a1, 0x7f0
	slli a1, a1, 12            # stack top 0x7f0000
	movi a8, 0x100
	slli a8, a8, 8             # HARNESS = 0x10000
	movi a10, 0x100
	slli a10, a10, 12          # INPUT = 0x100000
	callx8 a8
	mov a5, a10                # bytes of output
	movi a4, 0x300
	slli a4, a4, 12            # OUTPUT = 0x300000
	movi a3, 1
	movi a2, 4
	.byte 0x00, 0x51, 0x00     # write(1, OUTPUT, bytes)
	movi a3, 0
	movi a2, 1
	.byte 0x00, 0x51, 0x00     # exit(0)
