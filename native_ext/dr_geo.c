/* dr_geo.c: see dr_geo.h; codegen/kernel/reference.py offset_latlon_e7 is the specification. */
#include "dr_geo.h"

#include "dr_math.h"

#define DR_RAD_PER_DEG_E7 (1.74532925199433e-9f) /* rad per 1e-7 degree */
#define DR_INV_A_PER_M (1.567855942887398e-7f)   /* 1 / a, 1/m */
#define DR_INV_A1E2_PER_M (1.578422502906847e-7f)   /* 1 / (a (1 - e^2)), 1/m */
#define DR_LON_HALF_TURN_E7 (1800000000)         /* 180 degrees in 1e-7 degree */

float dr_sin_half_pi(float x) {
    float x2 = x * x;
    /* x - x^3/3! + x^5/5! - ... - x^11/11! + x^13/13!, Horner form */
    return x * (1.0f - x2 * (1.0f / 6.0f -
                x2 * (1.0f / 120.0f -
                x2 * (1.0f / 5040.0f -
                x2 * (1.0f / 362880.0f -
                x2 * (1.0f / 39916800.0f -
                x2 * (1.0f / 6227020800.0f)))))));
}

void dr_offset_latlon(int32_t lat_e7, int32_t lon_e7, float east_m, float north_m, int32_t *lat_out,
                      int32_t *lon_out) {
    float s = dr_sin_half_pi((float)lat_e7 * DR_RAD_PER_DEG_E7);
    float s2 = s * s;
    float w2 = 1.0f - DR_WGS84_E2 * s2;
    float k = dr_inv_sqrt(w2);
    float inv_m = w2 * w2 * k * DR_INV_A1E2_PER_M; /* 1 / M = (1 - e^2 sin^2)^1.5 / (a (1 - e^2)) */
    float inv_n = w2 * k * DR_INV_A_PER_M;         /* 1 / N = (1 - e^2 sin^2)^0.5 / a */
    float inv_cos = dr_inv_sqrt(1.0f - s2);        /* 0 at a pole: no longitude change there */
    int32_t lon = lon_e7 + dr_round(east_m * inv_n * inv_cos * DR_DEG_E7_PER_RAD);
    if (lon > DR_LON_HALF_TURN_E7) {
        lon = (lon - DR_LON_HALF_TURN_E7) - DR_LON_HALF_TURN_E7;
    } else if (lon < -DR_LON_HALF_TURN_E7) {
        lon = (lon + DR_LON_HALF_TURN_E7) + DR_LON_HALF_TURN_E7;
    }
    *lat_out = lat_e7 + dr_round(north_m * inv_m * DR_DEG_E7_PER_RAD);
    *lon_out = lon;
}
