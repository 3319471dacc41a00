/* Point-GN geometry kernels: centroid, farthest point sampling, k nearest neighbours.
 *
 * Compiled WITHOUT -ffast-math and with -ffp-contract=off: every distance is
 * rounded exactly like the oracle's torch ops ((dx*dx + dy*dy) + dz*dz, each
 * product and sum rounded to float32), so FPS and kNN choices are identical,
 * ties included (lowest index wins).
 */
#include <math.h>
#include <stdint.h>
#include <string.h>
#if defined(__AVX512F__) || defined(__AVX2__)
#include <immintrin.h>
#endif

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
 * a branch per 16 points (BENCHMARKS.md, "FPS on AVX-512"). */
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
                const __m512 dx = _mm512_sub_ps(_mm512_loadu_ps(x + o), vx);
                const __m512 dy = _mm512_sub_ps(_mm512_loadu_ps(y + o), vy);
                const __m512 dz = _mm512_sub_ps(_mm512_loadu_ps(z + o), vz);
                __m512 d = _mm512_mul_ps(dx, dx);
                d = _mm512_add_ps(d, _mm512_mul_ps(dy, dy));
                d = _mm512_add_ps(d, _mm512_mul_ps(dz, dz));
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

/* The encoder's FPS: start at the point farthest from the torch-exact centroid of
 * xyz ((n, 3) AoS copy of x, y, z). */
void pgn_fps(const float *xyz, const float *x, const float *y, const float *z, int64_t n,
             int64_t m, int64_t *idx, float *min_d) {
    float c[3];
    pgn_centroid(xyz, n, c);
    for (int64_t i = 0; i < n; ++i) {
        float dx = x[i] - c[0], dy = y[i] - c[1], dz = z[i] - c[2];
        float d = dx * dx;
        d = d + dy * dy;
        d = d + dz * dz;
        min_d[i] = d;
    }
    pgn_fps_from(x, y, z, n, m, first_argmax(min_d, n), idx, min_d);
}

/* Keys sort by (distance, index): distances are >= +0 so their bit patterns
 * order like the values. */
static inline uint64_t make_key(float d, int64_t i) {
    uint32_t b;
    memcpy(&b, &d, 4);
    return ((uint64_t)b << 32) | (uint64_t)(uint32_t)i;
}

/* Partition keys so that keys[0..k) are the k smallest (unordered). */
static void select_k(uint64_t *keys, int64_t n, int64_t k) {
    int64_t lo = 0, hi = n - 1;
    while (hi > lo) {
        /* median of three pivot */
        int64_t mid = lo + (hi - lo) / 2;
        uint64_t a = keys[lo], b = keys[mid], c = keys[hi];
        uint64_t p = a < b ? (b < c ? b : (a < c ? c : a)) : (a < c ? a : (b < c ? c : b));
        int64_t i = lo, j = hi;
        while (i <= j) {
            while (keys[i] < p) i++;
            while (keys[j] > p) j--;
            if (i <= j) { uint64_t t = keys[i]; keys[i] = keys[j]; keys[j] = t; i++; j--; }
        }
        if (k - 1 <= j) hi = j;
        else if (k - 1 >= i) lo = i;
        else return;
    }
}

/* Insertion sort of a few keys. */
static void sort_small(uint64_t *keys, int64_t n) {
    for (int64_t i = 1; i < n; ++i) {
        uint64_t v = keys[i];
        int64_t j = i - 1;
        while (j >= 0 && keys[j] > v) { keys[j + 1] = keys[j]; --j; }
        keys[j + 1] = v;
    }
}

static inline int64_t count_le(const float *d, int64_t n, float tau) {
    int64_t c = 0, i = 0;
#if defined(__AVX512F__)
    /* per-lane int32 counters bumped under the compare mask (no mask moved to a general
     * register per vector), two chains, summed once */
    const __m512 vt = _mm512_set1_ps(tau);
    const __m512i one = _mm512_set1_epi32(1);
    __m512i c0 = _mm512_setzero_si512(), c1 = c0;
    for (; i + 32 <= n; i += 32) {
        c0 = _mm512_mask_add_epi32(c0, _mm512_cmp_ps_mask(_mm512_loadu_ps(d + i), vt,
                                                          _CMP_LE_OQ), c0, one);
        c1 = _mm512_mask_add_epi32(c1, _mm512_cmp_ps_mask(_mm512_loadu_ps(d + i + 16), vt,
                                                          _CMP_LE_OQ), c1, one);
    }
    c = _mm512_reduce_add_epi32(_mm512_add_epi32(c0, c1));
#elif defined(__AVX2__)
    /* AVX2: per-lane int32 counters (a true compare is -1: subtract it), four chains,
     * summed once (movemask + popcount per vector was slower on Zen 3) */
    const __m256 vt = _mm256_set1_ps(tau);
    __m256i c0 = _mm256_setzero_si256(), c1 = c0, c2 = c0, c3 = c0;
    for (; i + 32 <= n; i += 32) {
        c0 = _mm256_sub_epi32(c0, _mm256_castps_si256(
            _mm256_cmp_ps(_mm256_loadu_ps(d + i), vt, _CMP_LE_OQ)));
        c1 = _mm256_sub_epi32(c1, _mm256_castps_si256(
            _mm256_cmp_ps(_mm256_loadu_ps(d + i + 8), vt, _CMP_LE_OQ)));
        c2 = _mm256_sub_epi32(c2, _mm256_castps_si256(
            _mm256_cmp_ps(_mm256_loadu_ps(d + i + 16), vt, _CMP_LE_OQ)));
        c3 = _mm256_sub_epi32(c3, _mm256_castps_si256(
            _mm256_cmp_ps(_mm256_loadu_ps(d + i + 24), vt, _CMP_LE_OQ)));
    }
    const __m256i cs = _mm256_add_epi32(_mm256_add_epi32(c0, c1), _mm256_add_epi32(c2, c3));
    __m128i h = _mm_add_epi32(_mm256_castsi256_si128(cs), _mm256_extracti128_si256(cs, 1));
    h = _mm_add_epi32(h, _mm_shuffle_epi32(h, 0x4e));
    h = _mm_add_epi32(h, _mm_shuffle_epi32(h, 0xb1));
    c = _mm_cvtsi128_si32(h);
#endif
    for (; i < n; ++i) c += d[i] <= tau;
    return c;
}

#if defined(__AVX2__) && !defined(__AVX512F__)
/* compress_lut[m]: the set lanes of the 8-bit mask m, in order, then zeros (one byte each) */
static uint8_t compress_lut[256][8];
__attribute__((constructor)) static void init_compress_lut(void) {  /* at library load */
    for (int m = 0; m < 256; ++m) {
        int c = 0;
        for (int l = 0; l < 8; ++l) if (m >> l & 1) compress_lut[m][c++] = (uint8_t)l;
        for (; c < 8; ++c) compress_lut[m][c] = 0;
    }
}
#endif

/* Indices i with d[i] <= lo into a (returns count); lo < d[i] <= hi into b (*nb). */
static int64_t split3(const float *d, int64_t n, float lo, float hi, int32_t *a, int32_t *b,
                      int64_t *nb) {
    int64_t ca = 0, cb = 0, i = 0;
#if defined(__AVX512F__)
    const __m512i step = _mm512_set1_epi32(16);
    __m512i idx = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    const __m512 vlo = _mm512_set1_ps(lo), vhi = _mm512_set1_ps(hi);
    for (; i + 16 <= n; i += 16) {
        const __m512 v = _mm512_loadu_ps(d + i);
        const __mmask16 ma = _mm512_cmp_ps_mask(v, vlo, _CMP_LE_OQ);
        const __mmask16 mb = _mm512_cmp_ps_mask(v, vhi, _CMP_LE_OQ) & (__mmask16)~ma;
        /* compress into a register, then a plain store: compressing straight to
         * memory is microcoded and slow on AMD Zen 4 */
        _mm512_storeu_si512((void *)(a + ca), _mm512_maskz_compress_epi32(ma, idx));
        _mm512_storeu_si512((void *)(b + cb), _mm512_maskz_compress_epi32(mb, idx));
        ca += __builtin_popcount(ma);
        cb += __builtin_popcount(mb);
        idx = _mm512_add_epi32(idx, step);
    }
#elif defined(__AVX2__)
    /* AVX2 has no compress: a table of lane permutations for each 8-bit mask moves the
     * selected indices to the front, then one plain 8-lane store */
    const __m256i step = _mm256_set1_epi32(8);
    __m256i idx = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    const __m256 vlo = _mm256_set1_ps(lo), vhi = _mm256_set1_ps(hi);
    for (; i + 8 <= n; i += 8) {
        const __m256 v = _mm256_loadu_ps(d + i);
        const unsigned ma = (unsigned)_mm256_movemask_ps(_mm256_cmp_ps(v, vlo, _CMP_LE_OQ));
        const unsigned mb = (unsigned)_mm256_movemask_ps(_mm256_cmp_ps(v, vhi, _CMP_LE_OQ)) & ~ma;
        _mm256_storeu_si256((__m256i *)(a + ca), _mm256_permutevar8x32_epi32(
            idx, _mm256_cvtepu8_epi32(_mm_loadl_epi64((const __m128i *)compress_lut[ma]))));
        ca += __builtin_popcount(ma);
        /* the middle band (a few points, scattered: a branch on it mispredicts) */
        _mm256_storeu_si256((__m256i *)(b + cb), _mm256_permutevar8x32_epi32(
            idx, _mm256_cvtepu8_epi32(_mm_loadl_epi64((const __m128i *)compress_lut[mb]))));
        cb += __builtin_popcount(mb);
        idx = _mm256_add_epi32(idx, step);
    }
#endif
    for (; i < n; ++i) {
        a[ca] = (int32_t)i;
        b[cb] = (int32_t)i;
        const int in_a = d[i] <= lo;
        ca += in_a;
        cb += !in_a && d[i] <= hi;
    }
    *nb = cb;
    return ca;
}

/* k nearest points (keys by distance then index) of each of s centres.
 * x, y, z: SoA points (n each); cx, cy, cz: centres (s each); nb: (s, k) int32 out,
 * unordered within a row, plus 16 int32 of writable slack after the last row.
 * dist: n floats scratch; keys: 2 n + 32 uint64 scratch.
 *
 * The k-th smallest distance is bracketed by counting passes (interpolation,
 * never shrinking the bracket by less than 10 %): points at or below the low end
 * are in, and only the few between the ends are ordered by (distance, index). */
void pgn_knn(const float *x, const float *y, const float *z, int64_t n, const float *cx,
             const float *cy, const float *cz, int64_t s, int64_t k, int32_t *nb, float *dist,
             uint64_t *keys) {
    int32_t *mid = (int32_t *)keys;          /* n + 16 int32 */
    uint64_t *mk = keys + (n + 16);          /* up to n keys */
    for (int64_t c = 0; c < s; ++c) {
        int32_t *row = nb + c * k;
        if (k >= n) {
            for (int64_t i = 0; i < n; ++i) row[i] = (int32_t)i;
            continue;
        }
        const float px = cx[c], py = cy[c], pz = cz[c];
        float dmax = 0.0f;
#pragma omp simd reduction(max:dmax)
        for (int64_t i = 0; i < n; ++i) {
            float dx = px - x[i], dy = py - y[i], dz = pz - z[i];
            float d = dx * dx;
            d = d + dy * dy;
            d = d + dz * dz;
            dist[i] = d;
            dmax = d > dmax ? d : dmax;
        }
        /* invariant: count(d <= lo) = clo < k <= chi = count(d <= hi) */
        float lo = -1.0f, hi = dmax;
        int64_t clo = 0, chi = n;
        for (int it = 0; it < 12 && chi - clo > 24; ++it) {
            const float base = lo < 0.0f ? 0.0f : lo;
            float tau = base + (hi - base) * (float)(((double)k - 0.5 - (double)clo)
                                                   / (double)(chi - clo));
            const float w = hi - base;
            if (tau < base + 0.1f * w) tau = base + 0.1f * w;
            if (tau > hi - 0.1f * w) tau = hi - 0.1f * w;
            if (!(tau > lo && tau < hi)) break;  /* bracket can no longer shrink (ties) */
            const int64_t ct = count_le(dist, n, tau);
            if (ct >= k) { hi = tau; chi = ct; } else { lo = tau; clo = ct; }
        }
        int64_t nm = 0;
        const int64_t nin = split3(dist, n, lo, hi, row, mid, &nm);
        (void)nin;
        /* order the middle by (distance, index); take what is still needed */
        for (int64_t j = 0; j < nm; ++j) mk[j] = make_key(dist[mid[j]], mid[j]);
        const int64_t need = k - clo;
        if (nm <= 32) sort_small(mk, nm);
        else select_k(mk, nm, need);
        for (int64_t j = 0; j < need; ++j) row[clo + j] = (int32_t)(mk[j] & 0xffffffffu);
    }
}
