/* The coarse pass of bank/search.py over packed 4-bit codes: half the bytes of int8.
 *
 * A row of r codes in [-7, 7] (r a multiple of 32) is r / 2 bytes, in chunks of up to 64
 * bytes: in a chunk of L bytes starting at byte b, byte b + t holds code 2b + t + 8 in its
 * low 4 bits and code 2b + L + t + 8 in its high 4 bits (bank/index_basis.py `pack_codes`
 * writes it). Each chunk's low and high halves then meet contiguous slices of the int8
 * query, so unpacking is an AND and a shift, and a chunk is two unsigned x signed byte dot
 * products (vpdpbusd where the CPU has VNNI). score = sum (u - 8) q = sum u q - 8 sum q.
 *
 * pgn_scan_i4(packed, n, r, q, out): out[i] = sum_j code[i][j] * q[j], q (r,) int8 in
 * [-127, 127]: the integers pgn_scan_i8 computes from the unpacked codes.
 * pgn_scan_i4_multi: the same for nq queries, out (nq, n), the rows read once per block.
 */
#include <stdint.h>
#if defined(__AVX512BW__) || defined(__AVX2__)
#include <immintrin.h>
#endif

enum { CHUNK = 64, MAX_CHUNKS = 16 };   /* rows of up to 2,048 codes take the SIMD paths */
/* Software prefetch this many bytes ahead of the row being scanned: after idle time the
 * hardware prefetchers alone left a 11 MB pass at 1.46 ms instead of 1.01 (16 rows of
 * 288 codes ahead; BENCHMARKS.md, "Third session of 2026-12-03"). */
enum { PREFETCH_AHEAD = 2304 };

static int32_t query_sum(const int8_t *q, int64_t r) {
    int32_t s = 0;
    for (int64_t j = 0; j < r; ++j) s += q[j];
    return s;
}

/* The plain loop over one row: the definition the SIMD paths must equal. */
static int32_t row_plain(const uint8_t *row, int64_t r, const int8_t *q) {
    const int64_t p = r / 2;
    int32_t acc = 0;
    for (int64_t b = 0; b < p; b += CHUNK) {
        const int64_t len = p - b < CHUNK ? p - b : CHUNK;
        for (int64_t t = 0; t < len; ++t) {
            acc += ((int32_t)(row[b + t] & 15) - 8) * q[2 * b + t];
            acc += ((int32_t)(row[b + t] >> 4) - 8) * q[2 * b + len + t];
        }
    }
    return acc;
}

#if defined(__AVX512BW__)
/* sum over 4 bytes of u (unsigned) x q (signed) added into acc's int32 lanes (exact:
 * 4 x 15 x 127 fits easily) */
static inline __m512i dot_u8s8(__m512i acc, __m512i u, __m512i q) {
#if defined(__AVX512VNNI__)
    return _mm512_dpbusd_epi32(acc, u, q);
#else
    const __m512i pairs = _mm512_maddubs_epi16(u, q);     /* <= 2 x 15 x 127: no saturation */
    return _mm512_add_epi32(acc, _mm512_madd_epi16(pairs, _mm512_set1_epi16(1)));
#endif
}

static void scan_avx512(const uint8_t *packed, int64_t n, int64_t r, const int8_t *q,
                        int32_t *out) {
    const int64_t p = r / 2, nc = (p + CHUNK - 1) / CHUNK;
    __m512i qlo[MAX_CHUNKS], qhi[MAX_CHUNKS];
    __mmask64 mask[MAX_CHUNKS];
    for (int64_t c = 0; c < nc; ++c) {
        const int64_t b = c * CHUNK, len = p - b < CHUNK ? p - b : CHUNK;
        mask[c] = len == CHUNK ? ~(__mmask64)0 : (((__mmask64)1 << len) - 1);
        qlo[c] = _mm512_maskz_loadu_epi8(mask[c], q + 2 * b);
        qhi[c] = _mm512_maskz_loadu_epi8(mask[c], q + 2 * b + len);
    }
    const int32_t offset = 8 * query_sum(q, r);
    const __m512i nib = _mm512_set1_epi8(15);
    for (int64_t i = 0; i < n; ++i) {
        const uint8_t *row = packed + i * p;
        if ((i + 1) * p + PREFETCH_AHEAD < n * p)
            for (int64_t o = 0; o < p; o += 64) __builtin_prefetch(row + PREFETCH_AHEAD + o);
        __m512i acc = _mm512_setzero_si512(), acc2 = acc;
        for (int64_t c = 0; c < nc; ++c) {
            const __m512i v = _mm512_maskz_loadu_epi8(mask[c], row + c * CHUNK);
            acc = dot_u8s8(acc, _mm512_and_si512(v, nib), qlo[c]);
            acc2 = dot_u8s8(acc2, _mm512_and_si512(_mm512_srli_epi16(v, 4), nib), qhi[c]);
        }
        out[i] = _mm512_reduce_add_epi32(_mm512_add_epi32(acc, acc2)) - offset;
    }
}
#elif defined(__AVX2__)
/* One piece of 32 or 16 bytes of a chunk: lo/hi nibbles against their query slices. */
static inline __m256i piece_avx2(__m256i acc, __m256i v, __m256i ql, __m256i qh) {
    const __m256i nib = _mm256_set1_epi8(15), ones = _mm256_set1_epi16(1);
    const __m256i lo = _mm256_and_si256(v, nib);
    const __m256i hi = _mm256_and_si256(_mm256_srli_epi16(v, 4), nib);
    acc = _mm256_add_epi32(acc, _mm256_madd_epi16(_mm256_maddubs_epi16(lo, ql), ones));
    return _mm256_add_epi32(acc, _mm256_madd_epi16(_mm256_maddubs_epi16(hi, qh), ones));
}

static inline __m256i load_piece(const void *p, int64_t bytes) {    /* 32, or 16 zero-extended */
    return bytes == 32 ? _mm256_loadu_si256(p) : _mm256_zextsi128_si256(_mm_loadu_si128(p));
}

static void scan_avx2(const uint8_t *packed, int64_t n, int64_t r, const int8_t *q,
                      int32_t *out) {
    /* pieces of 32 bytes (16 at a chunk's end when its length is 16 or 48) */
    const int64_t p = r / 2;
    int64_t start[2 * MAX_CHUNKS], size[2 * MAX_CHUNKS], np = 0;
    __m256i ql[2 * MAX_CHUNKS], qh[2 * MAX_CHUNKS];
    for (int64_t b = 0; b < p; b += CHUNK) {
        const int64_t len = p - b < CHUNK ? p - b : CHUNK;
        for (int64_t t = 0; t < len; t += 32, ++np) {
            start[np] = b + t;
            size[np] = len - t < 32 ? len - t : 32;
            ql[np] = load_piece(q + 2 * b + t, size[np]);
            qh[np] = load_piece(q + 2 * b + len + t, size[np]);
        }
    }
    const int32_t offset = 8 * query_sum(q, r);
    for (int64_t i = 0; i < n; ++i) {
        const uint8_t *row = packed + i * p;
        if ((i + 1) * p + PREFETCH_AHEAD < n * p)   /* one prefetch a cache line */
            for (int64_t o = 0; o < p; o += 64) __builtin_prefetch(row + PREFETCH_AHEAD + o);
        __m256i acc = _mm256_setzero_si256();
        for (int64_t k = 0; k < np; ++k)
            acc = piece_avx2(acc, load_piece(row + start[k], size[k]), ql[k], qh[k]);
        const __m128i s = _mm_add_epi32(_mm256_castsi256_si128(acc), _mm256_extracti128_si256(acc, 1));
        const __m128i s2 = _mm_add_epi32(s, _mm_shuffle_epi32(s, 0x4e));
        out[i] = _mm_cvtsi128_si32(_mm_add_epi32(s2, _mm_shuffle_epi32(s2, 0xb1))) - offset;
    }
}
#endif

void pgn_scan_i4(const uint8_t *packed, int64_t n, int64_t r, const int8_t *q, int32_t *out) {
    if (r % 32 == 0 && r / 2 <= MAX_CHUNKS * CHUNK) {
#if defined(__AVX512BW__)
        scan_avx512(packed, n, r, q, out);
        return;
#elif defined(__AVX2__)
        scan_avx2(packed, n, r, q, out);
        return;
#endif
    }
    for (int64_t i = 0; i < n; ++i) out[i] = row_plain(packed + i * (r / 2), r, q);
}

/* A batch: blocks of rows that stay in L1 while every query passes over them. */
enum { SCAN4_BLOCK = 128 };

void pgn_scan_i4_multi(const uint8_t *packed, int64_t n, int64_t r, const int8_t *q,
                       int64_t nq, int32_t *out) {
    if (nq == 1) {
        pgn_scan_i4(packed, n, r, q, out);
        return;
    }
    for (int64_t i0 = 0; i0 < n; i0 += SCAN4_BLOCK) {
        const int64_t m = n - i0 < SCAN4_BLOCK ? n - i0 : SCAN4_BLOCK;
        for (int64_t b = 0; b < nq; ++b)
            pgn_scan_i4(packed + i0 * (r / 2), m, r, q + b * r, out + b * n + i0);
    }
}
