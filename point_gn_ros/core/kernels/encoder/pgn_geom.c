/* Point-GN geometry kernels: centroid and farthest point sampling (the kNN: pgn_knn.c).
 *
 * Built exact (no fast-math, no contraction: SOURCE_FLAGS): every distance is
 * rounded exactly like the oracle's torch ops ((dx*dx + dy*dy) + dz*dz, each
 * product and sum rounded to float32), so FPS choices are identical,
 * ties included (lowest index wins).
 */
#include <math.h>
#include <stdint.h>
#include <string.h>
#if defined(__AVX512F__) || defined(__AVX2__)
#include <immintrin.h>
#endif

#include "pgn_geom.h"

/* One column of torch's CPU `sum(dim=0)` over a contiguous (n, 3) float32 tensor
 * (ATen SumKernel.cpp cascade_sum -> scalar_outer_sum -> row_sum with ilp 4):
 * four strided partials, each a 4-level cascade; tail into partial 0; then
 * partial 0 += 1, 2, 3. Reproduced bit for bit so the FPS start point (farthest
 * from the centroid) ties exactly like the oracle. */
static float torch_col_sum3(const float *col, int64_t n) {
    const int64_t size = n / 4;
    int bits = 0;
    if (size > 1) {
        uint64_t v = (uint64_t)(size - 1);
        while (v) { bits++; v >>= 1; }
    }
    const int lp = bits / 4 > 4 ? bits / 4 : 4;
    const int64_t ls = (int64_t)1 << lp, lm = ls - 1;
    float acc[4][4] = {{0}};
    int64_t i = 0;
    while (i + ls <= size) {
        for (int64_t j = 0; j < ls; ++j, ++i)
            for (int k = 0; k < 4; ++k) acc[0][k] += col[(i * 4 + k) * 3];
        for (int j = 1; j < 4; ++j) {
            for (int k = 0; k < 4; ++k) { acc[j][k] += acc[j - 1][k]; acc[j - 1][k] = 0.0f; }
            if (i & (lm << (j * lp))) break;
        }
    }
    for (; i < size; ++i)
        for (int k = 0; k < 4; ++k) acc[0][k] += col[(i * 4 + k) * 3];
    for (int j = 1; j < 4; ++j)
        for (int k = 0; k < 4; ++k) acc[0][k] += acc[j][k];
    float s = acc[0][0];
    for (int64_t r = size * 4; r < n; ++r) s += col[r * 3];
    s += acc[0][1];
    s += acc[0][2];
    s += acc[0][3];
    return s;
}

/* torch.mean(xyz, dim=0) for a contiguous (n, 3) float32 array, bit-exact. */
void pgn_centroid(const float *xyz, int64_t n, float *out) {
    for (int a = 0; a < 3; ++a) out[a] = torch_col_sum3(xyz + a, n) / (float)n;
}

/* First index of the maximum of v[0..n) (all finite). Block maxima first so the
 * scan for the first maximal element touches few elements. */
static int64_t first_argmax(const float *v, int64_t n) {
    float best = v[0];
    int64_t bi = 0;
    int64_t i = 0;
    for (; i + 16 <= n; i += 16) {
        float m = v[i];
#pragma omp simd reduction(max:m)
        for (int j = 0; j < 16; ++j) m = v[i + j] > m ? v[i + j] : m;
        if (m > best) {
            best = m;
            for (int j = 0; j < 16; ++j) if (v[i + j] == m) { bi = i + j; break; }
        }
    }
    for (; i < n; ++i) if (v[i] > best) { best = v[i]; bi = i; }
    return bi;
}

/* One FPS step's update of point i's distance to the chosen set (scalar loops): the
 * oracle's rounding ((dx^2 + dy^2) + dz^2, no contraction); the first step starts from
 * +inf in the oracle: min(inf, d) = d. Returns the new min_d[i]. */
static inline float fps_update(const float *x, const float *y, const float *z, int64_t i,
                               float px, float py, float pz, int64_t it, float *min_d) {
    float dx = x[i] - px, dy = y[i] - py, dz = z[i] - pz;
    float d = dx * dx;
    d = d + dy * dy;
    d = d + dz * dz;
    float md = (it == 0 || d < min_d[i]) ? d : min_d[i];
    min_d[i] = md;
    return md;
}

#if defined(__AVX2__) || defined(__AVX512F__)
/* The vector FPS loops' step end: the lanes' (max, first index) pairs -> the first maximum
 * over points [0, done), then points [done, n) (indices above all others) updated from the
 * current point cur and compared strictly. Returns the next point. */
static int64_t fps_pick(const float *v, const int32_t *ix, int lanes, const float *x,
                        const float *y, const float *z, int64_t done, int64_t n, int64_t it,
                        float *min_d, int64_t cur) {
    const float px = x[cur], py = y[cur], pz = z[cur];
    float best = v[0];
    int64_t bix = ix[0];
    for (int l = 1; l < lanes; ++l)
        if (v[l] > best || (v[l] == best && ix[l] < bix)) { best = v[l]; bix = ix[l]; }
    for (int64_t i = done; i < n; ++i) {
        const float md = fps_update(x, y, z, i, px, py, pz, it, min_d);
        if (md > best) { best = md; bix = i; }
    }
    return bix;
}
#endif

/* Farthest point sampling from a given start over SoA coordinates x, y, z (n each)
 * -> idx[0..m). min_d: scratch of n floats. Same rounding and ties (first maximum)
 * as the oracle's and numpy's loops. */
#if defined(__AVX2__) && !defined(__AVX512F__)
/* (value, index) pairs per lane: keep the larger value, on a tie the smaller index. */
static inline void fps_merge(__m256 *bv, __m256i *bi, __m256 v, __m256i i) {
    const __m256 gt = _mm256_cmp_ps(v, *bv, _CMP_GT_OQ);
    const __m256i lt = _mm256_cmpgt_epi32(*bi, i);
    const __m256 take = _mm256_or_ps(gt, _mm256_and_ps(_mm256_cmp_ps(v, *bv, _CMP_EQ_OQ),
                                                       _mm256_castsi256_ps(lt)));
    *bv = _mm256_blendv_ps(*bv, v, take);
    *bi = _mm256_castps_si256(_mm256_blendv_ps(_mm256_castsi256_ps(*bi),
                                               _mm256_castsi256_ps(i), take));
}

/* pgn_fps_from for n >= 32 on AVX2: the running (max, first index) kept per lane in four
 * independent chains (a horizontal max and a branch per block of 16 were the cost),
 * merged once per step. Same distances, same first maximum. */
static void fps_from_avx2(const float *x, const float *y, const float *z, int64_t n,
                          int64_t m, int64_t cur, int64_t *idx, float *min_d) {
    const int64_t n32 = n / 32 * 32;
    for (int64_t it = 0; it < m; ++it) {
        idx[it] = cur;
        const float px = x[cur], py = y[cur], pz = z[cur];
        const __m256 vx = _mm256_set1_ps(px), vy = _mm256_set1_ps(py), vz = _mm256_set1_ps(pz);
        __m256 bv[4];
        __m256i bi[4], vi[4];
        for (int j = 0; j < 4; ++j) {
            bv[j] = _mm256_set1_ps(-1.0f);
            bi[j] = _mm256_setzero_si256();
            vi[j] = _mm256_add_epi32(_mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7),
                                     _mm256_set1_epi32(8 * j));
        }
        const __m256i step = _mm256_set1_epi32(32);
        for (int64_t i = 0; i < n32; i += 32) {
            for (int j = 0; j < 4; ++j) {
                const int64_t o = i + 8 * j;
                const __m256 dx = _mm256_sub_ps(_mm256_loadu_ps(x + o), vx);
                const __m256 dy = _mm256_sub_ps(_mm256_loadu_ps(y + o), vy);
                const __m256 dz = _mm256_sub_ps(_mm256_loadu_ps(z + o), vz);
                __m256 d = _mm256_mul_ps(dx, dx);
                d = _mm256_add_ps(d, _mm256_mul_ps(dy, dy));
                d = _mm256_add_ps(d, _mm256_mul_ps(dz, dz));
                /* the first step starts from +inf in the oracle: min(inf, d) = d */
                const __m256 md = it == 0 ? d : _mm256_min_ps(d, _mm256_loadu_ps(min_d + o));
                _mm256_storeu_ps(min_d + o, md);
                /* strictly greater: each lane keeps its first maximum */
                const __m256 gt = _mm256_cmp_ps(md, bv[j], _CMP_GT_OQ);
                bv[j] = _mm256_blendv_ps(bv[j], md, gt);
                bi[j] = _mm256_castps_si256(_mm256_blendv_ps(_mm256_castsi256_ps(bi[j]),
                                                             _mm256_castsi256_ps(vi[j]), gt));
                vi[j] = _mm256_add_epi32(vi[j], step);
            }
        }
        fps_merge(&bv[0], &bi[0], bv[1], bi[1]);
        fps_merge(&bv[2], &bi[2], bv[3], bi[3]);
        fps_merge(&bv[0], &bi[0], bv[2], bi[2]);
        float v8[8];
        int32_t i8[8];
        _mm256_storeu_ps(v8, bv[0]);
        _mm256_storeu_si256((__m256i *)i8, bi[0]);
        cur = fps_pick(v8, i8, 8, x, y, z, n32, n, it, min_d, cur);
    }
}
#endif

#if defined(__AVX512F__)
/* fps_from_avx2 with 16 lanes and masks: the running (max, first index) per lane in four
 * chains of 16 points, merged once per step. Same distances (mul, then add: no
 * contraction), same first maximum. pgn_fps_from's block loop spent a horizontal max and
 * a branch per 16 points. */
static inline void fps_merge16(__m512 *bv, __m512i *bi, __m512 v, __m512i i) {
    const __mmask16 take = _mm512_cmp_ps_mask(v, *bv, _CMP_GT_OQ)
                           | (_mm512_cmp_ps_mask(v, *bv, _CMP_EQ_OQ)
                              & _mm512_cmpgt_epi32_mask(*bi, i));
    *bv = _mm512_mask_mov_ps(*bv, take, v);
    *bi = _mm512_mask_mov_epi32(*bi, take, i);
}

static void fps_from_avx512(const float *x, const float *y, const float *z, int64_t n,
                            int64_t m, int64_t cur, int64_t *idx, float *min_d) {
    const int64_t n64 = n / 64 * 64;
    const __m512i lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    const __m512i step = _mm512_set1_epi32(64);
    for (int64_t it = 0; it < m; ++it) {
        idx[it] = cur;
        const float px = x[cur], py = y[cur], pz = z[cur];
        const __m512 vx = _mm512_set1_ps(px), vy = _mm512_set1_ps(py), vz = _mm512_set1_ps(pz);
        __m512 bv[4];
        __m512i bi[4], vi[4];
        for (int j = 0; j < 4; ++j) {
            bv[j] = _mm512_set1_ps(-1.0f);
            bi[j] = _mm512_setzero_si512();
            vi[j] = _mm512_add_epi32(lane, _mm512_set1_epi32(16 * j));
        }
        for (int64_t i = 0; i < n64; i += 64) {
            for (int j = 0; j < 4; ++j) {
                const int64_t o = i + 16 * j;
                const __m512 d = sqdist16(x, y, z, o, vx, vy, vz);
                /* the first step starts from +inf in the oracle: min(inf, d) = d */
                const __m512 md = it == 0 ? d : _mm512_min_ps(d, _mm512_loadu_ps(min_d + o));
                _mm512_storeu_ps(min_d + o, md);
                /* strictly greater: each lane keeps its first maximum */
                const __mmask16 gt = _mm512_cmp_ps_mask(md, bv[j], _CMP_GT_OQ);
                bv[j] = _mm512_mask_mov_ps(bv[j], gt, md);
                bi[j] = _mm512_mask_mov_epi32(bi[j], gt, vi[j]);
                vi[j] = _mm512_add_epi32(vi[j], step);
            }
        }
        fps_merge16(&bv[0], &bi[0], bv[1], bi[1]);
        fps_merge16(&bv[2], &bi[2], bv[3], bi[3]);
        fps_merge16(&bv[0], &bi[0], bv[2], bi[2]);
        float v16[16];
        int32_t i16[16];
        _mm512_storeu_ps(v16, bv[0]);
        _mm512_storeu_si512((void *)i16, bi[0]);
        cur = fps_pick(v16, i16, 16, x, y, z, n64, n, it, min_d, cur);
    }
}
#endif

void pgn_fps_from(const float *x, const float *y, const float *z, int64_t n, int64_t m,
                  int64_t cur, int64_t *idx, float *min_d) {
#if defined(__AVX2__) && !defined(__AVX512F__)
    if (n >= 32) {
        fps_from_avx2(x, y, z, n, m, cur, idx, min_d);
        return;
    }
#endif
#if defined(__AVX512F__)
    if (n >= 64) {
        fps_from_avx512(x, y, z, n, m, cur, idx, min_d);
        return;
    }
#endif
    for (int64_t it = 0; it < m; ++it) {
        idx[it] = cur;
        const float px = x[cur], py = y[cur], pz = z[cur];
        int64_t bi = 0;
        float best = -1.0f;
        int64_t i = 0;
        for (; i + 16 <= n; i += 16) {
            float bm = -1.0f;
#pragma omp simd reduction(max:bm)
            for (int j = 0; j < 16; ++j) {
                float dx = x[i + j] - px, dy = y[i + j] - py, dz = z[i + j] - pz;
                float d = dx * dx;
                d = d + dy * dy;
                d = d + dz * dz;
                /* the first iteration starts from +inf in the oracle: min(inf, d) = d */
                float md = (it == 0 || d < min_d[i + j]) ? d : min_d[i + j];
                min_d[i + j] = md;
                bm = md > bm ? md : bm;
            }
            if (bm > best) { best = bm; bi = i; }
        }
        int64_t tail_best = -1;
        for (; i < n; ++i) {
            const float md = fps_update(x, y, z, i, px, py, pz, it, min_d);
            if (md > best) { best = md; tail_best = i; }
        }
        if (tail_best >= 0) {
            cur = tail_best;
        } else {
            cur = bi;
            for (int j = 0; j < 16; ++j) if (min_d[bi + j] == best) { cur = bi + j; break; }
        }
    }
}

#if defined(__AVX512F__)
/* pgn_fps_from over a slab's points (pgn_slab.c: in buckets along one axis), each step
 * updating only the buckets where a distance can fall. A point's distance to the chosen set
 * falls only if its distance to the new point is smaller, and that distance is at least the
 * point's axis offset squared (as rounded); every current distance is at most the new
 * point's own, D. So the points outside pgn_slab_range(D) keep theirs exactly, and the step
 * updates the others. Each block of 16 points keeps its largest distance and, among equals,
 * its lowest index; the pick is the largest over the blocks, then the lowest index: the
 * points pgn_fps_from picks, in order. AVX-512 only: plain loops of this were 3x slower than
 * pgn_fps_from's vector loops (the 16-lane reductions). */
static void fps_slab(const pgn_slab *sl, const float *x, const float *y, const float *z,
                     int64_t m, int64_t cur, int64_t *idx) {
    const int64_t n = sl->n, nbk = (n + 15) / 16, ng = (nbk + 15) / 16;
    const float *sx = sl->s[0], *sy = sl->s[1], *sz = sl->s[2];
    const float *ca = sl->axis == 0 ? x : (sl->axis == 1 ? y : z);
    float *md = sl->fmd, *bmax = sl->bmax;
    int32_t *barg = sl->barg;
    for (int64_t k = nbk; k < 16 * ng; ++k) { bmax[k] = -2.0f; barg[k] = INT32_MAX; }
    float D = INFINITY;
    for (int64_t it = 0; it < m; ++it) {
        idx[it] = cur;
        const __m512 vx = _mm512_set1_ps(x[cur]), vy = _mm512_set1_ps(y[cur]);
        const __m512 vz = _mm512_set1_ps(z[cur]);
        int64_t k0 = 0, k1 = nbk;
        if (it) {
            int64_t p0, p1;
            pgn_slab_range(sl, ca[cur], D, &p0, &p1);
            k0 = p0 / 16;
            k1 = (p1 + 15) / 16;
        }
        for (int64_t k = k0; k < k1; ++k) {
            const int64_t o = 16 * k;
            const __m512 d = sqdist16(sx, sy, sz, o, vx, vy, vz);
            __m512 v;
            if (it == 0) {  /* from +inf: min(inf, d) = d; the last block's slack: -1 */
                const __mmask16 in = n - o >= 16 ? (__mmask16)0xffff
                                                 : (__mmask16)((1u << (n - o)) - 1u);
                v = _mm512_mask_mov_ps(_mm512_set1_ps(-1.0f), in, d);
            } else {
                const __m512 old = _mm512_loadu_ps(md + o);
                v = _mm512_mask_mov_ps(old, _mm512_cmp_ps_mask(d, old, _CMP_LT_OQ), d);
            }
            _mm512_storeu_ps(md + o, v);
            const float bm = _mm512_reduce_max_ps(v);
            bmax[k] = bm;
            barg[k] = _mm512_mask_reduce_min_epi32(
                _mm512_cmp_ps_mask(v, _mm512_set1_ps(bm), _CMP_EQ_OQ),
                _mm512_loadu_si512((const void *)(sl->idx + o)));
        }
        __m512 mv = _mm512_loadu_ps(bmax);
        for (int64_t g = 1; g < ng; ++g) mv = _mm512_max_ps(mv, _mm512_loadu_ps(bmax + 16 * g));
        D = _mm512_reduce_max_ps(mv);
        __m512i mi = _mm512_set1_epi32(INT32_MAX);
        for (int64_t g = 0; g < ng; ++g)
            mi = _mm512_mask_min_epi32(mi, _mm512_cmp_ps_mask(_mm512_loadu_ps(bmax + 16 * g),
                                                              _mm512_set1_ps(D), _CMP_EQ_OQ),
                                       mi, _mm512_loadu_si512((const void *)(barg + 16 * g)));
        cur = _mm512_reduce_min_epi32(mi);
    }
}
#endif

/* The encoder's FPS: start at the point farthest from the torch-exact centroid of
 * xyz ((n, 3) AoS copy of x, y, z); over a slab's buckets where sl is given. */
void pgn_fps_in(const float *xyz, const float *x, const float *y, const float *z, int64_t n,
                int64_t m, int64_t *idx, float *min_d, const pgn_slab *sl) {
    float c[3];
    pgn_centroid(xyz, n, c);
    for (int64_t i = 0; i < n; ++i) {
        float dx = x[i] - c[0], dy = y[i] - c[1], dz = z[i] - c[2];
        float d = dx * dx;
        d = d + dy * dy;
        d = d + dz * dz;
        min_d[i] = d;
    }
#if defined(__AVX512F__)
    if (sl && sl->n == n) {
        fps_slab(sl, x, y, z, m, first_argmax(min_d, n), idx);
        return;
    }
#endif
    (void)sl;
    pgn_fps_from(x, y, z, n, m, first_argmax(min_d, n), idx, min_d);
}

/* pgn_fps_in without a slab. */
void pgn_fps(const float *xyz, const float *x, const float *y, const float *z, int64_t n,
             int64_t m, int64_t *idx, float *min_d) {
    pgn_fps_in(xyz, x, y, z, n, m, idx, min_d, NULL);
}
