/*
 * harness.c: drives the kernel inside a relocated dr_native.mpy on qemu-system-xtensa, as the binding does on the
 * board (codegen/natmod/qemu_xtensa.py builds it with the LLVM route, links it with mpy_ld, loads both).
 *
 * The input block (little-endian 32-bit words) holds the entry points of the kernel functions in the loaded module,
 * the workspace and output addresses, and the steps; every step writes to the output: the instructions the call
 * took (ICOUNT), the kernel's return code, out[6] and the first state floats. Returns the output's size in bytes.
 *
 *   magic "DRX1" | algorithm (0 seed, 1 fused) | steps | state floats reported | workspace | output |
 *   10 function addresses (FN_*) | steps: kind ('C', 'P', 'G') | samples n | payload
 *   C: int16 samples[6n]   P: int16 samples[6n], int32 dt_us[n]   G (n = 4): float ve vn de dn (sim_steps.h)
 */
#include <stddef.h>
#include <stdint.h>

#include "dr_board.h"
#include "dr_fused.h"
#include "dr_kernel.h"
#include "sim_steps.h"

#define HARNESS_MAGIC (0x31585244u) /* "DRX1" */
#define HEADER_WORDS (16)
#define OUT_FLOATS (6)

enum {
    FN_CONFIG_INIT,
    FN_STATE_INIT,
    FN_CALIBRATE,
    FN_PROCESS,
    FN_FUSED_CONFIG_INIT,
    FN_FUSED_STATE_INIT,
    FN_FUSED_CALIBRATE,
    FN_FUSED_PROCESS,
    FN_FUSED_POSITION,
    FN_FUSED_GPS,
    FN_COUNT
};

typedef struct {
    __typeof__(dr_config_init) *config_init;
    __typeof__(dr_state_init) *state_init;
    __typeof__(dr_calibrate) *calibrate;
    __typeof__(dr_process) *process;
    __typeof__(dr_fused_config_init) *fused_config_init;
    __typeof__(dr_fused_state_init) *fused_state_init;
    __typeof__(dr_fused_calibrate) *fused_calibrate;
    __typeof__(dr_fused_process) *fused_process;
    __typeof__(dr_fused_position) *fused_position;
    __typeof__(dr_fused_gps) *fused_gps;
} kernel_fns;

typedef struct {
    dr_config kcfg;
    dr_state st;
    dr_fused_config fcfg;
    dr_fused_state fst;
    float out[OUT_FLOATS];
    float scratch[3 * DR_BLOCK_SAMPLES];
} workspace;

/* The output record of one step; returns the next free word. */
static uint32_t *report(uint32_t *at, uint32_t took, int32_t code, const float *out, const float *state,
                        uint32_t floats) {
    uint32_t i;
    *at++ = took;
    *at++ = (uint32_t)code;
    for (i = 0; i < OUT_FLOATS; i++) {
        ((float *)at)[i] = out[i];
    }
    at += OUT_FLOATS;
    for (i = 0; i < floats; i++) {
        ((float *)at)[i] = state[i];
    }
    return at + floats;
}

uint32_t mpy_init(const uint32_t *input) {
    const kernel_fns *fn = (const kernel_fns *)(input + 6);
    workspace *w = (workspace *)input[4];
    uint32_t *at = (uint32_t *)input[5];
    uint32_t *start = at;
    const uint32_t *step = input + HEADER_WORDS;
    int fused = input[1] == 1u;
    uint32_t steps = input[2], floats = input[3], k, t0, t1;
    const float *state = fused ? (const float *)&w->fst : (const float *)&w->st;
    if (input[0] != HARNESS_MAGIC) {
        return 0;
    }
    fn->config_init(&w->kcfg);
    if (fused) {
        fn->fused_config_init(&w->fcfg);
        fn->fused_state_init(&w->fst);
    } else {
        fn->state_init(&w->st);
    }
    for (k = 0; k < steps; k++) {
        sim_step s;
        int32_t code = 0;
        step = sim_step_read(step, &s);
        if (s.kind == 'C') {
            t0 = sim_instructions();
            code = fused ? fn->fused_calibrate(&w->kcfg, &w->fst, s.samples, (int32_t)s.n)
                         : fn->calibrate(&w->kcfg, &w->st, s.samples, (int32_t)s.n);
            t1 = sim_instructions();
        } else if (s.kind == 'P') {
            t0 = sim_instructions();
            if (fused) {
                code = fn->fused_process(&w->kcfg, &w->fcfg, &w->fst, s.samples, s.dt_us, (int32_t)s.n, w->out);
            } else {
                code = fn->process(&w->kcfg, &w->st, w->scratch, s.samples, s.dt_us, (int32_t)s.n, w->out, 0);
            }
            t1 = sim_instructions();
        } else {
            const float *gps = s.values;
            t0 = sim_instructions();
            fn->fused_position(&w->fcfg, &w->fst, gps[0], gps[1], gps[2], gps[3]);
            fn->fused_gps(&w->fcfg, &w->fst, gps[0], gps[1]);
            t1 = sim_instructions();
        }
        at = report(at, t1 - t0, code, w->out, state, floats);
    }
    return (uint32_t)((at - start) * sizeof(uint32_t));
}
