/*
 * dr_geo.h: local ENU metres -> latitude/longitude offset from an anchor fix, without float32 loss.
 *
 * A latitude held in a float32 resolves ~0.6 m, so the anchor stays an integer of 1e-7 degree (1.1 cm of latitude)
 * and only the offset (metres to kilometres) is a float.
 */
#ifndef DR_GEO_H
#define DR_GEO_H

#include <stdint.h>

#define DR_WGS84_A_M (6378137.0f)          /* m, WGS-84 semi-major axis */
#define DR_WGS84_E2 (0.00669437999014f)    /* WGS-84 first eccentricity squared */
#define DR_DEG_E7_PER_RAD (572957795.1308f) /* 1e-7 degree per radian */

/* Returns sin(x) for |x| <= pi/2 rad (Taylor series to x^13, error below 1e-7). */
float dr_sin_half_pi(float x);

/* Writes the anchor (lat_e7, lon_e7, 1e-7 degree) moved by east_m and north_m metres into *lat_out, *lon_out
 * (1e-7 degree, rounded to nearest, longitude wrapped into [-180, 180] degrees), using the WGS-84 meridian and
 * prime-vertical radii of curvature at the anchor. */
void dr_offset_latlon(int32_t lat_e7, int32_t lon_e7, float east_m, float north_m, int32_t *lat_out,
                      int32_t *lon_out);

#endif /* DR_GEO_H */
