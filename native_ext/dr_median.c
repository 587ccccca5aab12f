/* dr_median.c: see dr_median.h. */
#include "dr_median.h"

/* Gaps 2^k - 1 (Hibbard): each is the previous shifted right, so no table and no division are needed. */
void dr_sort(float *x, int32_t count) {
    int32_t gap = 1;
    while (gap * 2 + 1 < count) {
        gap = gap * 2 + 1;
    }
    for (; gap > 0; gap >>= 1) {
        int32_t i;
        for (i = gap; i < count; i++) {
            float v = x[i];
            int32_t j = i;
            while (j >= gap && x[j - gap] > v) {
                x[j] = x[j - gap];
                j -= gap;
            }
            x[j] = v;
        }
    }
}

float dr_median(float *x, int32_t count) {
    int32_t half = count >> 1;
    dr_sort(x, count);
    if (count & 1) {
        return x[half];
    }
    return (x[half - 1] + x[half]) * 0.5f;
}

int32_t dr_block_median(float *x, int32_t count, int32_t block, float *out) {
    int32_t blocks = 0;
    int32_t start;
    if (block < 1 || count < 0) {
        return -1;
    }
    for (start = 0; start + block <= count; start += block) {
        out[blocks++] = dr_median(x + start, block);
    }
    if (start != count) {
        return -1;
    }
    return blocks;
}
