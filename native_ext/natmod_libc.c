/*
 * natmod_libc.c: memset and memcpy for the dynamic native module (Makefile SRC only; the user C module links the
 * firmware's C library instead). A native module links no C library, yet GCC turns the kernel's zeroing and copying
 * loops into calls to these two (armv6m and armv7m at -Os); they forward to the firmware's own via mp_fun_table.
 */
#include "py/dynruntime.h"

void *memset(void *s, int c, size_t n) {
    return mp_fun_table.memset_(s, c, n);
}

void *memcpy(void *dst, const void *src, size_t n) {
    return mp_fun_table.memmove_(dst, src, n);
}
