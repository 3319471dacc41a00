/* The encoder's geometry, built without fast-math (pgn_geom.c: FPS; pgn_knn*.c: kNN), for
 * its callers: pgn_steps.h (the encoder's steps) and pgn_prepare.c (midpoint_fill's
 * neighbours). Hashed with the sources for the kernel cache key (kernels/__init__.py).
 */
#ifndef PGN_GEOM_H
#define PGN_GEOM_H

#include <math.h>
#include <stdint.h>
#if defined(__AVX512F__)
#include <immintrin.h>
#endif

void pgn_fps(const float *xyz, const float *x, const float *y, const float *z, int64_t n,
             int64_t m, int64_t *idx, float *min_d);
void pgn_knn(const float *x, const float *y, const float *z, int64_t n, const float *cx,
             const float *cy, const float *cz, int64_t s, int64_t k, int32_t *nb, float *dist,
             uint64_t *keys, float guess);
float pgn_knn_guess(const float *x, const float *y, const float *z, int64_t n, int64_t k);
/* The points in buckets along one axis (pgn_slab.c), for pgn_fps_in and pgn_knn_in. */
typedef struct pgn_slab {
    int64_t n;
    int axis;
    const float *s[3];    /* x, y, z in that order */
    const int32_t *idx;   /* each one's index among the points */
    const uint16_t *idx16; /* the same as 16 bits, 32 more (0) past n */
    float lo, sc;         /* bucket of v: (v - lo) sc, clamped to [0, 255] */
    const int32_t *bend;  /* (256,) where each bucket's points end */
    float *bmax;          /* FPS scratch (pgn_fps_in): each block of 16 points' largest */
    int32_t *barg;        /* distance and its point (lowest index among equals) */
    float *fmd;           /* FPS scratch: each point's distance to the chosen set (n + 16) */
} pgn_slab;
/* The bucket of value v along the slab's axis, clamped to [0, 255]: monotone in v. */
static inline int32_t slab_bucket(const pgn_slab *sl, float v) {
    const float t = (v - sl->lo) * sl->sc;
    return t < 0.0f || t != t ? 0 : (t >= 255.0f ? 255 : (int32_t)t);
}
/* The positions [*p0, *p1) of the buckets that hold every point within squared distance f
 * of a point at qa on the slab's axis: its axis offset squared, as rounded, is at most f.
 * The ends are sqrt(f) and 0.1 % more away: far more than the roundings of the offset, of
 * its square and of the ends themselves; the buckets are monotone in the value. */
static inline void pgn_slab_range(const pgn_slab *sl, float qa, float f, int64_t *p0,
                                  int64_t *p1) {
    const float r = sqrtf(f) * 1.001f + fabsf(qa) * 1e-6f + 1e-30f;
    const int32_t b0 = slab_bucket(sl, qa - r), b1 = slab_bucket(sl, qa + r);
    *p0 = b0 ? sl->bend[b0 - 1] : 0;
    *p1 = sl->bend[b1];
}
#if defined(__AVX512F__)
/* Squared distances of points o..o+15 (SoA x, y, z) to (vx, vy, vz), rounded as the oracle's:
 * (dx*dx + dy*dy) + dz*dz, each product and sum a float32. For FPS and the kNN, which are
 * built without fast-math (in a fast-math file the compiler could fuse them). */
static inline __m512 sqdist16(const float *x, const float *y, const float *z, int64_t o,
                              __m512 vx, __m512 vy, __m512 vz) {
    const __m512 dx = _mm512_sub_ps(_mm512_loadu_ps(x + o), vx);
    const __m512 dy = _mm512_sub_ps(_mm512_loadu_ps(y + o), vy);
    const __m512 dz = _mm512_sub_ps(_mm512_loadu_ps(z + o), vz);
    __m512 d = _mm512_mul_ps(dx, dx);
    d = _mm512_add_ps(d, _mm512_mul_ps(dy, dy));
    return _mm512_add_ps(d, _mm512_mul_ps(dz, dz));
}
#endif
int64_t pgn_slab_floats(int64_t n);
int pgn_slab_build(const float *x, const float *y, const float *z, int64_t n, int64_t k,
                   float *buf, pgn_slab *sl);
void pgn_fps_in(const float *xyz, const float *x, const float *y, const float *z, int64_t n,
                int64_t m, int64_t *idx, float *min_d, const pgn_slab *sl);
void pgn_knn_in(const float *x, const float *y, const float *z, int64_t n, const float *cx,
                const float *cy, const float *cz, int64_t s, int64_t k, int32_t *nb,
                float *dist, uint64_t *keys, float guess, const pgn_slab *sl);

#endif
