/* The encoder's geometry, built without fast-math (pgn_geom.c: FPS; pgn_knn.c: kNN), for
 * its callers: pgn_phases.h (the encoder's steps) and pgn_prepare.c (midpoint_fill's
 * neighbours). Hashed with the sources for the kernel cache key (kernels/__init__.py).
 */
#ifndef PGN_GEOM_H
#define PGN_GEOM_H

#include <stdint.h>

void pgn_fps(const float *xyz, const float *x, const float *y, const float *z, int64_t n,
             int64_t m, int64_t *idx, float *min_d);
void pgn_knn(const float *x, const float *y, const float *z, int64_t n, const float *cx,
             const float *cy, const float *cz, int64_t s, int64_t k, int32_t *nb, float *dist,
             uint64_t *keys, float guess);
float pgn_knn_guess(const float *x, const float *y, const float *z, int64_t n, int64_t k);

#endif
