/* The coarse pass of bank/index.py over packed 4-bit codes: half the bytes of int8.
 *
 * A row of r codes in [-7, 7] (r a multiple of 32) is r / 2 bytes, in chunks of up to 64
 * bytes: in a chunk of L bytes starting at byte b, byte b + t holds code 2b + t + 8 in its
 * low 4 bits and code 2b + L + t + 8 in its high 4 bits (bank/index.py `pack_codes`
 * writes it). Each chunk's low and high halves then meet contiguous slices of the int8
 * query, so unpacking is an AND and a shift, and a chunk is two unsigned x signed byte dot
 * products (vpdpbusd where the CPU has VNNI). score = sum (u - 8) q = sum u q - 8 sum q.
 *
 * pgn_scan_i4(packed, n, r, q, out): out[i] = sum_j code[i][j] * q[j], q (r,) int8 in
 * [-127, 127]: the integers pgn_scan_i8 computes from the unpacked codes.
 * pgn_scan_i4_multi: the same for nq queries, out (nq, n), the rows read once per block.
 */
#include <stdint.h>
#include <stdlib.h>
#if defined(__AVX512BW__) || defined(__AVX2__)
#include <immintrin.h>
#endif

enum { CHUNK = 64, MAX_CHUNKS = 16 };   /* rows of up to 2,048 codes take the SIMD paths */
/* Software prefetch this many bytes ahead of the row being scanned (16 rows of 288 codes):
 * after idle time the hardware prefetchers alone do not keep the pass at memory speed. */
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

/* A query's chunks (its int8 slices against each chunk's low and high nibbles), set up
 * once per query, not per block of rows. */
typedef struct {
    __m512i lo[MAX_CHUNKS], hi[MAX_CHUNKS];
    __mmask64 mask[MAX_CHUNKS];
    int64_t nc;
    int32_t offset;
} q4_t;

static void q4_prepare(q4_t *s, const int8_t *q, int64_t r) {
    const int64_t p = r / 2;
    s->nc = (p + CHUNK - 1) / CHUNK;
    for (int64_t c = 0; c < s->nc; ++c) {
        const int64_t b = c * CHUNK, len = p - b < CHUNK ? p - b : CHUNK;
        s->mask[c] = len == CHUNK ? ~(__mmask64)0 : (((__mmask64)1 << len) - 1);
        s->lo[c] = _mm512_maskz_loadu_epi8(s->mask[c], q + 2 * b);
        s->hi[c] = _mm512_maskz_loadu_epi8(s->mask[c], q + 2 * b + len);
    }
    s->offset = 8 * query_sum(q, r);
}

/* One row's 16 lane partial sums over nc chunks; lo, hi, mask: the query's (q4_t). */
static inline __attribute__((always_inline)) __m512i row_acc(
        const uint8_t *row, int64_t nc, const __m512i *lo, const __m512i *hi,
        const __mmask64 *mask) {
    const __m512i nib = _mm512_set1_epi8(15);
    __m512i acc = _mm512_setzero_si512();
    for (int64_t c = 0; c < nc; ++c) {
        const __m512i v = _mm512_maskz_loadu_epi8(mask[c], row + c * CHUNK);
        acc = dot_u8s8(acc, _mm512_and_si512(v, nib), lo[c]);
        acc = dot_u8s8(acc, _mm512_and_si512(_mm512_srli_epi16(v, 4), nib), hi[c]);
    }
    return acc;
}

static inline __m512 addi(__m512 a, __m512 b) {
    return _mm512_castsi512_ps(_mm512_add_epi32(_mm512_castps_si512(a), _mm512_castps_si512(b)));
}

/* 16 rows' lane partials a[k] -> lane k holds row k's sum: a halving tree of shuffles and
 * adds (as the stage-1 lanes kernel's red16), ~2 operations a row instead of a horizontal
 * sum of ~9 for each. Integer sums: the same totals in any order. */
static inline __m512i sum16(const __m512i *a) {
    __m512 s[8];
    for (int i = 0; i < 8; ++i) {
        const __m512 x = _mm512_castsi512_ps(a[2 * i]), y = _mm512_castsi512_ps(a[2 * i + 1]);
        s[i] = addi(_mm512_shuffle_f32x4(x, y, 0x44), _mm512_shuffle_f32x4(x, y, 0xEE));
    }
    for (int i = 0; i < 4; ++i)
        s[i] = addi(_mm512_shuffle_f32x4(s[2 * i], s[2 * i + 1], 0x88),
                    _mm512_shuffle_f32x4(s[2 * i], s[2 * i + 1], 0xDD));
    for (int i = 0; i < 2; ++i)
        s[i] = addi(_mm512_shuffle_ps(s[2 * i], s[2 * i + 1], 0x44),
                    _mm512_shuffle_ps(s[2 * i], s[2 * i + 1], 0xEE));
    const __m512 t = addi(_mm512_shuffle_ps(s[0], s[1], 0x88),
                          _mm512_shuffle_ps(s[0], s[1], 0xDD));
    return _mm512_castps_si512(_mm512_permutexvar_ps(
        _mm512_setr_epi32(0, 4, 8, 12, 1, 5, 9, 13, 2, 6, 10, 14, 3, 7, 11, 15), t));
}

/* Rows in groups of 16 (sum16), NC chunks a row: for NC <= 4 the query's chunks are held
 * in registers (NC a constant; read through s they were reloaded for every row, and loads
 * were what the loop waited on), NC = 0: s->nc chunks read through s. */
#define PGN_SCAN4(NAME, NC)                                                               \
    static void NAME(const uint8_t *packed, int64_t n, int64_t p, const q4_t *s,          \
                     int32_t *out) {                                                      \
        const int64_t nc = NC ? NC : s->nc;                                               \
        __m512i lo_[NC ? NC : 1], hi_[NC ? NC : 1];                                        \
        __mmask64 mk_[NC ? NC : 1];                                                       \
        for (int64_t c = 0; c < (NC ? NC : 0); ++c) {                                     \
            lo_[c] = s->lo[c]; hi_[c] = s->hi[c]; mk_[c] = s->mask[c];                    \
        }                                                                                 \
        const __m512i *lo = NC ? lo_ : s->lo, *hi = NC ? hi_ : s->hi;                     \
        const __mmask64 *mask = NC ? mk_ : s->mask;                                       \
        const __m512i off = _mm512_set1_epi32(s->offset);                                 \
        int64_t i = 0;                                                                    \
        for (; i + 16 <= n; i += 16) {                                                    \
            const uint8_t *rows = packed + i * p;                                         \
            if ((i + 16) * p + PREFETCH_AHEAD < n * p)                                    \
                for (int64_t o = 0; o < 16 * p; o += 64)                                  \
                    __builtin_prefetch(rows + PREFETCH_AHEAD + o);                        \
            __m512i acc[16];                                                              \
            for (int k = 0; k < 16; ++k) acc[k] = row_acc(rows + k * p, nc, lo, hi, mask); \
            _mm512_storeu_si512((void *)(out + i), _mm512_sub_epi32(sum16(acc), off));   \
        }                                                                                 \
        for (; i < n; ++i)                                                                \
            out[i] = _mm512_reduce_add_epi32(row_acc(packed + i * p, nc, lo, hi, mask))   \
                     - s->offset;                                                         \
    }
PGN_SCAN4(scan_nc1, 1)
PGN_SCAN4(scan_nc2, 2)
PGN_SCAN4(scan_nc3, 3)
PGN_SCAN4(scan_nc4, 4)
PGN_SCAN4(scan_any, 0)
#undef PGN_SCAN4

static void scan_avx512(const uint8_t *packed, int64_t n, int64_t p, const q4_t *s,
                        int32_t *out) {
    switch (s->nc) {
        case 1: scan_nc1(packed, n, p, s, out); break;
        case 2: scan_nc2(packed, n, p, s, out); break;
        case 3: scan_nc3(packed, n, p, s, out); break;
        case 4: scan_nc4(packed, n, p, s, out); break;
        default: scan_any(packed, n, p, s, out); break;
    }
}

/* A batch's block of rows with the nibbles already split (u: per row, per chunk, the low
 * then the high nibbles as bytes, 2 NC vectors): each query then spends only its 2 NC dot
 * products a row, not also the 3 NC operations of the split. */
#define PGN_SCAN4U(NAME, NC)                                                              \
    static void NAME(const __m512i *u, int64_t n, const q4_t *s, int32_t *out) {          \
        __m512i lo[NC], hi[NC];                                                           \
        for (int c = 0; c < NC; ++c) { lo[c] = s->lo[c]; hi[c] = s->hi[c]; }              \
        const __m512i off = _mm512_set1_epi32(s->offset);                                 \
        int64_t i = 0;                                                                    \
        for (; i + 16 <= n; i += 16) {                                                    \
            __m512i acc[16];                                                              \
            for (int k = 0; k < 16; ++k) {                                                \
                const __m512i *r = u + (i + k) * 2 * NC;                                  \
                acc[k] = _mm512_setzero_si512();                                          \
                for (int c = 0; c < NC; ++c) {                                            \
                    acc[k] = dot_u8s8(acc[k], r[2 * c], lo[c]);                           \
                    acc[k] = dot_u8s8(acc[k], r[2 * c + 1], hi[c]);                       \
                }                                                                         \
            }                                                                             \
            _mm512_storeu_si512((void *)(out + i), _mm512_sub_epi32(sum16(acc), off));   \
        }                                                                                 \
        for (; i < n; ++i) {                                                              \
            const __m512i *r = u + i * 2 * NC;                                            \
            __m512i acc = _mm512_setzero_si512();                                         \
            for (int c = 0; c < NC; ++c) {                                                \
                acc = dot_u8s8(acc, r[2 * c], lo[c]);                                     \
                acc = dot_u8s8(acc, r[2 * c + 1], hi[c]);                                 \
            }                                                                             \
            out[i] = _mm512_reduce_add_epi32(acc) - s->offset;                            \
        }                                                                                 \
    }
PGN_SCAN4U(scan_u1, 1)
PGN_SCAN4U(scan_u2, 2)
PGN_SCAN4U(scan_u3, 3)
PGN_SCAN4U(scan_u4, 4)
#undef PGN_SCAN4U
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
        q4_t s;
        q4_prepare(&s, q, r);
        scan_avx512(packed, n, r / 2, &s, out);
        return;
#elif defined(__AVX2__)
        scan_avx2(packed, n, r, q, out);
        return;
#endif
    }
    for (int64_t i = 0; i < n; ++i) out[i] = row_plain(packed + i * (r / 2), r, q);
}

/* A batch: blocks of rows that stay in L1 while every query passes over them (split into
 * nibbles first where a row has at most 4 chunks: blocks of SCAN4_UBLOCK). */
enum { SCAN4_BLOCK = 128, SCAN4_UBLOCK = 64 };

void pgn_scan_i4_multi(const uint8_t *packed, int64_t n, int64_t r, const int8_t *q,
                       int64_t nq, int32_t *out) {
    if (nq == 1) {
        pgn_scan_i4(packed, n, r, q, out);
        return;
    }
#if defined(__AVX512BW__)
    q4_t *s = r % 32 == 0 && r / 2 <= MAX_CHUNKS * CHUNK ? aligned_alloc(64, sizeof(q4_t) * nq)
                                                         : NULL;
    if (s != NULL) {   /* each query set up once */
        for (int64_t b = 0; b < nq; ++b) q4_prepare(&s[b], q + b * r, r);
        const int64_t nc = s[0].nc, p = r / 2;
        /* up to 4 chunks a row: the block's nibbles split once for all the queries (24 KB
         * a block at the scan section's 3 chunks, in L1); more: each query splits its own */
        __m512i *u = nc <= 4 ? aligned_alloc(64, sizeof(__m512i) * 2 * 4 * SCAN4_UBLOCK) : NULL;
        const __m512i nib = _mm512_set1_epi8(15);
        const int64_t blk = u ? SCAN4_UBLOCK : SCAN4_BLOCK;
        for (int64_t i0 = 0; i0 < n; i0 += blk) {
            const int64_t m = n - i0 < blk ? n - i0 : blk;
            if (u == NULL) {
                for (int64_t b = 0; b < nq; ++b)
                    scan_avx512(packed + i0 * p, m, p, &s[b], out + b * n + i0);
                continue;
            }
            for (int64_t k = 0; k < m; ++k)
                for (int64_t c = 0; c < nc; ++c) {
                    const __m512i v = _mm512_maskz_loadu_epi8(s[0].mask[c],
                                                              packed + (i0 + k) * p + c * CHUNK);
                    u[(k * nc + c) * 2] = _mm512_and_si512(v, nib);
                    u[(k * nc + c) * 2 + 1] = _mm512_and_si512(_mm512_srli_epi16(v, 4), nib);
                }
            for (int64_t b = 0; b < nq; ++b) {
                int32_t *o = out + b * n + i0;
                switch (nc) {
                    case 1: scan_u1(u, m, &s[b], o); break;
                    case 2: scan_u2(u, m, &s[b], o); break;
                    case 3: scan_u3(u, m, &s[b], o); break;
                    default: scan_u4(u, m, &s[b], o); break;
                }
            }
        }
        free(u);
        free(s);
        return;
    }
#endif
    for (int64_t i0 = 0; i0 < n; i0 += SCAN4_BLOCK) {
        const int64_t m = n - i0 < SCAN4_BLOCK ? n - i0 : SCAN4_BLOCK;
        for (int64_t b = 0; b < nq; ++b)
            pgn_scan_i4(packed + i0 * (r / 2), m, r, q + b * r, out + b * n + i0);
    }
}
