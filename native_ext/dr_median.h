/*
 * dr_median.h: block medians with numpy.median semantics (an even count gives the mean of the middle two values).
 */
#ifndef DR_MEDIAN_H
#define DR_MEDIAN_H

#include <stdint.h>

/* Sorts x[0..count-1] ascending in place (Shell sort: no recursion, no allocation, any count >= 0). */
void dr_sort(float *x, int32_t count);

/* Returns the median of x[0..count-1] (count >= 1), reordering x; for an even count (a + b) * 0.5f of the middle
 * two, the same float32 value numpy.median gives for a float32 array. */
float dr_median(float *x, int32_t count);

/* Writes out[j] = median of x[j*block .. j*block+block-1] for every whole block; x is reordered in place.
 * Returns the number of blocks, or -1 if block < 1 or count is not a multiple of block. */
int32_t dr_block_median(float *x, int32_t count, int32_t block, float *out);

#endif /* DR_MEDIAN_H */
