/* Exact dot products of a batch of queries with every bank row: the classifier's exact
 * kernel vote (bank/vote.py ExactSearch).
 *
 * pgn_dots_f32: out[b * n + i] = <feats[i], q[b]>, float32 rows.
 * pgn_dots_i8:  out[b * n + i] = <codes[i], q[b]> / norms[i], the int8 codes of a bank
 *               stored as int8 / int4 (its rows are codes / ||codes||): a quarter of the
 *               bytes of its float32 rows, so one query's scan reads 5 MB, not 20.
 *
 * Every dot is summed in one order fixed by this source whatever the batch: one 8-lane
 * partial sum over the row in steps of 8 (fused multiply-add where the CPU has it, by
 * intrinsic), a fixed tree over the lanes, then the tail in index order. The file is
 * compiled without fast-math and with -ffp-contract=off, so the compiler may not reorder or
 * fuse anything else: a query's result never depends on the queries or rows computed beside
 * it. Register tiles of 2 rows x 4 queries; the rows after the next pair are prefetched, and
 * every query passes over a pair while it is in cache, so a batch reads the bank once (a
 * BLAS GEMM at batch 1 is a matrix-vector product, and rounds by the batch's shape). A lone
 * query of int8 codes takes tiles of 8 rows: each row's sum is one chain of dependent FMAs,
 * and 2 chains left the core waiting on their latency (float32 rows are bound by memory:
 * there 8 rows a tile were slower).
 * The tile shape never changes a row's operations, only how many run side by side.
 */
#include <stdint.h>
#include <string.h>
#if defined(__AVX__)
#include <immintrin.h>
#endif

typedef float dv8 __attribute__((vector_size(32)));
typedef int8_t dc8 __attribute__((vector_size(8)));

static inline dv8 dload(const float *p) { dv8 v; memcpy(&v, p, sizeof(v)); return v; }

static inline dv8 dload_i8(const int8_t *p) {         /* exact: |code| <= 127 */
#if defined(__AVX2__)
    return (dv8)_mm256_cvtepi32_ps(_mm256_cvtepi8_epi32(_mm_loadl_epi64((const void *)p)));
#else
    dc8 v;
    memcpy(&v, p, sizeof(v));
    return __builtin_convertvector(v, dv8);
#endif
}

static inline dv8 dfma(dv8 a, dv8 b, dv8 c) {
#if defined(__FMA__)
    return (dv8)_mm256_fmadd_ps((__m256)a, (__m256)b, (__m256)c);
#else
    return a * b + c;
#endif
}

/* The lanes of s summed as ((t0 + t4) + (t1 + t5)) + ((t2 + t6) + (t3 + t7)). */
static inline float dsum(dv8 s) {
#if defined(__AVX__)
    const __m128 w = _mm_add_ps(_mm256_castps256_ps128((__m256)s),
                                _mm256_extractf128_ps((__m256)s, 1));
    const __m128 h = _mm_hadd_ps(w, w);               /* (w0 + w1, w2 + w3, ...) */
    return _mm_cvtss_f32(_mm_hadd_ps(h, h));
#else
    float t[8];
    memcpy(t, &s, sizeof(t));
    return ((t[0] + t[4]) + (t[1] + t[5])) + ((t[2] + t[6]) + (t[3] + t[7]));
#endif
}

/* R rows (1, 2 or 8) x G queries (1, 2 or 4; 1 when R = 8) of float32 rows (I8 = 0) or int8
 * codes (I8 = 1);
 * constant at each call, so each inlined copy keeps its R x G partial sums in registers. */
static inline __attribute__((always_inline)) void tile(
        const void *rows, const float *norms, int64_t i, int64_t n, int64_t d,
        const float *q, int64_t b, int R, int G, int I8, float *out) {
    const int64_t d8 = d / 8 * 8;
    const float *rf = (const float *)rows;
    const int8_t *rc = (const int8_t *)rows;
    dv8 acc[8][4] = {{{0}}};
    for (int64_t j = 0; j < d8; j += 8) {
        dv8 rv[8];
        for (int r = 0; r < R; ++r)
            rv[r] = I8 ? dload_i8(rc + (i + r) * d + j) : dload(rf + (i + r) * d + j);
        for (int g = 0; g < G; ++g) {
            const dv8 qv = dload(q + (b + g) * d + j);
            for (int r = 0; r < R; ++r) acc[r][g] = dfma(rv[r], qv, acc[r][g]);
        }
    }
    for (int r = 0; r < R; ++r)
        for (int g = 0; g < G; ++g) {
            const float *qb = q + (b + g) * d;
            float s = dsum(acc[r][g]);
            for (int64_t j = d8; j < d; ++j)
                s += (I8 ? (float)rc[(i + r) * d + j] : rf[(i + r) * d + j]) * qb[j];
            out[(b + g) * n + i + r] = I8 ? s / norms[i + r] : s;
        }
}

static inline __attribute__((always_inline)) void rows_tile(
        const void *rows, const float *norms, int64_t i, int64_t n, int64_t d,
        const float *q, int64_t nq, int R, int I8, float *out) {
    /* the rows after the next tile, ahead of use: one prefetch per cache line */
    const int64_t bytes = I8 ? 1 : 4;
    const char *base = (const char *)rows, *end = base + n * d * bytes;
    const char *ahead = base + (i + 2 * R) * d * bytes;
    for (int64_t o = 0; o < R * d * bytes && ahead + o < end; o += 64)
        __builtin_prefetch(ahead + o);
    int64_t b = 0;
    if (R == 8) { tile(rows, norms, i, n, d, q, 0, 8, 1, I8, out); return; }   /* nq == 1 */
    for (; b + 4 <= nq; b += 4) tile(rows, norms, i, n, d, q, b, R, 4, I8, out);
    if (b + 2 <= nq) { tile(rows, norms, i, n, d, q, b, R, 2, I8, out); b += 2; }
    if (b < nq) tile(rows, norms, i, n, d, q, b, R, 1, I8, out);
}

/* feats (n, d) and q (nq, d) row-major float32 -> out (nq, n). */
void pgn_dots_f32(const float *feats, int64_t n, int64_t d, const float *q, int64_t nq,
                  float *out) {
    int64_t i = 0;
    for (; i + 2 <= n; i += 2) rows_tile(feats, NULL, i, n, d, q, nq, 2, 0, out);
    if (i < n) rows_tile(feats, NULL, i, n, d, q, nq, 1, 0, out);
}

/* codes (n, d) int8, norms (n,) float32 > 0, q (nq, d) float32 -> out (nq, n). */
void pgn_dots_i8(const int8_t *codes, const float *norms, int64_t n, int64_t d,
                 const float *q, int64_t nq, float *out) {
    int64_t i = 0;
    if (nq == 1)
        for (; i + 8 <= n; i += 8) rows_tile(codes, norms, i, n, d, q, nq, 8, 1, out);
    for (; i + 2 <= n; i += 2) rows_tile(codes, norms, i, n, d, q, nq, 2, 1, out);
    if (i < n) rows_tile(codes, norms, i, n, d, q, nq, 1, 1, out);
}

/* ---- One query against 4-bit codes, 16 values to 8 bytes (kernels.pack_nibbles) ----
 * Byte b of a row's group g holds code 16 g + b in its low nibble and code 16 g + 8 + b in
 * its high one, each + 8. A bank stored as int4 has codes in [-7, 7], so half the bytes of
 * its int8 codes, and one load per 16 values instead of two. Every row's sum is
 * pgn_dots_i8's, operation for operation: the same 8-lane partial sums in index order
 * (d % 16 == 0: no tail), the same lane tree and division, so the cosines are the int8
 * scan's bit for bit. */
#if defined(__AVX2__)
static inline void dload_nib(const uint8_t *p, dv8 *lo, dv8 *hi) {
    const __m256i u = _mm256_cvtepu8_epi32(_mm_loadl_epi64((const void *)p));
    const __m256i e8 = _mm256_set1_epi32(8);
    *lo = (dv8)_mm256_cvtepi32_ps(_mm256_sub_epi32(_mm256_and_si256(u, _mm256_set1_epi32(15)),
                                                   e8));
    *hi = (dv8)_mm256_cvtepi32_ps(_mm256_sub_epi32(_mm256_srli_epi32(u, 4), e8));
}
#else
typedef int32_t di8 __attribute__((vector_size(32)));
typedef uint8_t du8 __attribute__((vector_size(8)));
static inline void dload_nib(const uint8_t *p, dv8 *lo, dv8 *hi) {
    du8 v;
    memcpy(&v, p, sizeof(v));
    const di8 u = __builtin_convertvector(v, di8);
    *lo = __builtin_convertvector((u & 15) - 8, dv8);
    *hi = __builtin_convertvector((u >> 4) - 8, dv8);
}
#endif

static inline __attribute__((always_inline)) void tile_nib(
        const uint8_t *packed, const float *norms, int64_t i, int64_t n, int64_t d,
        const float *q, int R, float *out) {
    const int64_t rb = d / 2;
    const uint8_t *ahead = packed + (i + 2 * R) * rb, *end = packed + n * rb;
    for (int64_t o = 0; o < R * rb && ahead + o < end; o += 64) __builtin_prefetch(ahead + o);
    dv8 acc[8] = {{0}};
    for (int64_t j = 0; j < d; j += 16) {
        const dv8 q0 = dload(q + j), q1 = dload(q + j + 8);
        for (int r = 0; r < R; ++r) {
            dv8 lo, hi;
            dload_nib(packed + (i + r) * rb + j / 2, &lo, &hi);
            acc[r] = dfma(lo, q0, acc[r]);
            acc[r] = dfma(hi, q1, acc[r]);
        }
    }
    for (int r = 0; r < R; ++r) out[i + r] = dsum(acc[r]) / norms[i + r];
}

/* packed (n, d / 2) uint8, d % 16 == 0; norms (n,) float32 > 0; q (d,) -> out (n,). */
void pgn_dots_i4(const uint8_t *packed, const float *norms, int64_t n, int64_t d,
                 const float *q, float *out) {
    int64_t i = 0;
    for (; i + 8 <= n; i += 8) tile_nib(packed, norms, i, n, d, q, 8, out);
    for (; i < n; ++i) tile_nib(packed, norms, i, n, d, q, 1, out);
}
