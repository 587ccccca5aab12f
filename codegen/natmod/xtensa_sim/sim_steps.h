/*
 * sim_steps.h: what the bare-metal harnesses on qemu-system-xtensa share (harness.c for dr_native.mpy's kernels,
 * eskf_harness.c for the error-state filter): the instruction counter boot.s starts, and the steps of the input
 * block. Each step is kind | n | payload (little-endian 32-bit words):
 *   'C': int16 samples[6n]   'P': int16 samples[6n], int32 dt_us[n]   any other kind: n words (floats)
 */
#ifndef DR_SIM_STEPS_H
#define DR_SIM_STEPS_H

#include <stdint.h>

typedef struct {
    uint32_t kind;           /* 'C', 'P' or a harness's own letter */
    uint32_t n;              /* samples (C, P) or payload words */
    const int16_t *samples;  /* C, P: [ax, ay, az, gx, gy, gz] counts per sample */
    const int32_t *dt_us;    /* P: microseconds per sample */
    const float *values;     /* any other kind: the n payload words */
} sim_step;

/* Returns ICOUNT, the instructions retired at interrupt level 0 since boot.s enabled the counter. */
static inline uint32_t sim_instructions(void) {
    uint32_t count;
    __asm__ volatile("rsr %0, icount" : "=r"(count));
    return count;
}

/* Decodes the step at `at` into s; returns where the next step starts. */
static inline const uint32_t *sim_step_read(const uint32_t *at, sim_step *s) {
    s->kind = at[0];
    s->n = at[1];
    s->samples = (const int16_t *)(at + 2);
    s->dt_us = (const int32_t *)(at + 2 + 3 * s->n);
    s->values = (const float *)(at + 2);
    if (s->kind == 'C') {
        return at + 2 + 3 * s->n;
    }
    if (s->kind == 'P') {
        return at + 2 + 4 * s->n;
    }
    return at + 2 + s->n;
}

#endif /* DR_SIM_STEPS_H */
