/* Stage 1 (16 < D <= 32) with neighbours in the lanes, AVX2 + FMA: pgn_avx512_lanes.c with
 * 8-float lanes, for CPUs without AVX-512 (PGN_AVX2). An axis's Gaussians are running
 * products U_{l+1} = U_l P from U_0 = A (2 exponentials per axis and 8 neighbours, one
 * block at the default sigma), T folded out of the products and back in on the results;
 * the offset half's rows transposed per centre, 4 channels at a time. Sixteen ymm registers
 * hold 8 groups' running products; their P are read from memory. */
#include "pgn_common.h"

#if defined(PGN_AVX2)
#define NG 8  /* groups of 8 neighbours a chunk: 64 neighbours */

/* 2^-t, exactly 0 where exp2_neg_avx2 clamps (t >= 125): an underflowing A must be 0, not
 * 2^-125, or the running products would grow it back (lanes_range_ok) */
static inline __m256 exp2_neg0(__m256 t) {
    return _mm256_and_ps(exp2_neg_avx2(t),
                         _mm256_cmp_ps(t, _mm256_set1_ps(125.0f), _CMP_LT_OQ));
}

/* 8 channels' lane partials V (8, 8) reduced over the lanes: lane c is channel c's max
 * (MAX) or sum. Rounds: 128-bit halves, pairs, neighbours; the last leaves channel 2 j + h
 * in lane 4 h + j, then one permute. */
#define PGN_RED8(NAME, OP)                                                               \
    static inline __m256 NAME(const float *V) {                                         \
        __m256 s[4];                                                                     \
        for (int i = 0; i < 4; ++i) {                                                    \
            const __m256 a = _mm256_load_ps(V + 16 * i), b = _mm256_load_ps(V + 16 * i + 8); \
            s[i] = OP(_mm256_permute2f128_ps(a, b, 0x20), _mm256_permute2f128_ps(a, b, 0x31)); \
        }                                                                                \
        for (int i = 0; i < 2; ++i)                                                      \
            s[i] = OP(_mm256_shuffle_ps(s[2 * i], s[2 * i + 1], 0x44),                   \
                      _mm256_shuffle_ps(s[2 * i], s[2 * i + 1], 0xEE));                  \
        const __m256 t = OP(_mm256_shuffle_ps(s[0], s[1], 0x88),                         \
                            _mm256_shuffle_ps(s[0], s[1], 0xDD));                        \
        return _mm256_permutevar8x32_ps(t, _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7));  \
    }
PGN_RED8(red8_max, _mm256_max_ps)
PGN_RED8(red8_add, _mm256_add_ps)
#undef PGN_RED8

/* One channel over a chunk's NG groups: w = (f + U) U into mx (valid lanes only unless
 * FULL) and sm; U steps to U P. F(i): the offset (row) or centre value of group i. */
#define PGN_CHANNEL(FULL, F)                                                             \
    for (int i = 0; i < NG; ++i) {                                                       \
        const __m256 w = _mm256_mul_ps(_mm256_add_ps(F(i), U[i]), U[i]);                 \
        U[i] = _mm256_mul_ps(U[i], _mm256_load_ps(PV + 8 * i));                          \
        mx = _mm256_max_ps(mx, FULL ? w                                                  \
                                    : _mm256_blendv_ps(ninf, w, _mm256_load_ps(VM + 8 * i))); \
        sm = _mm256_add_ps(sm, w);                                                       \
    }

/* As pgn_aggregate_lanes_avx512; scr: pgn_lanes_scratch(K) floats, 64-byte aligned. */
void pgn_aggregate_lanes_avx2(const float *feat, int64_t D, const int64_t *cidx,
                              const int32_t *nb, int64_t S, int64_t K, const float *vx,
                              float r, const lanes_t *lp, float *out, float *scr) {
    const int64_t Dp = padded(D), D2 = 2 * D, D2p = padded(D2), nc = lp->nc;
    const int64_t G = (K + 7) / 8, Kc = (K + 8 * NG - 1) / (8 * NG) * (8 * NG), Gc = Kc / 8;
    float *RT = scr;            /* (D, Kc): (row - cf) r / T by channel, 0 past K */
    float *WV = RT + D * Kc;    /* (3, Kc): clamped offsets by axis, 0 past K */
    float *PV = WV + 3 * Kc;    /* (NG * 8): a chunk's P of one axis */
    float *VM = PV + Kc;        /* (NG * 8): a chunk's valid-lane masks */
    float *MX = VM + Kc;        /* (2D, 8): per-lane max of each channel */
    float *SM = MX + 64 * 8;    /* (2D, 8): per-lane sum */
    float *acc = SM + 64 * 8, *rs = acc + 64, *ct = rs + 64, *t2 = ct + 64;
    const float invk = 1.0f / (float)K, W = lp->W;
    pgn_lanes_scales(lp, D2, r, rs, ct, t2);
    const __m256 ql = _mm256_set1_ps(lp->ql), nh2ql = _mm256_set1_ps(-lp->h2ql);
    const __m256 ninf = _mm256_set1_ps(-INFINITY), zero = _mm256_setzero_ps();
    const __m256i iota = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    memset(RT, 0, sizeof(float) * (size_t)((D + 3) * Kc));
    for (int64_t c = 0; c < S; ++c) {
        const float *cf = feat + cidx[c] * Dp;
        const int32_t *nr = nb + c * K;
        const float *vc = vx + c * K * 3;
        for (int64_t t = 0; t < K; ++t)
            for (int a = 0; a < 3; ++a) {
                const float v = vc[3 * t + a];
                WV[a * Kc + t] = v < -W ? -W : (v > W ? W : v);
            }
        /* rows by channel, 4 channels at a time: 128-bit half h of Y[m] holds row 4 h + m,
         * then a 4 x 4 transpose in each half */
        for (int64_t g = 0; g < G; ++g) {
            const int64_t nv = K - 8 * g < 8 ? K - 8 * g : 8;
            const __m256 vm = _mm256_castsi256_ps(
                _mm256_cmpgt_epi32(_mm256_set1_epi32((int32_t)nv), iota));
            const float *rows[8];
            for (int i = 0; i < 8; ++i)
                rows[i] = feat + (int64_t)nr[8 * g + (i < nv ? i : 0)] * Dp;
            for (int64_t k = 0; 4 * k < D; ++k) {
                __m256 Y[4];
                for (int m = 0; m < 4; ++m)
                    Y[m] = _mm256_insertf128_ps(
                        _mm256_castps128_ps256(_mm_load_ps(rows[m] + 4 * k)),
                        _mm_load_ps(rows[4 + m] + 4 * k), 1);
                const __m256d t0 = _mm256_castps_pd(_mm256_unpacklo_ps(Y[0], Y[1]));
                const __m256d t1 = _mm256_castps_pd(_mm256_unpackhi_ps(Y[0], Y[1]));
                const __m256d t2v = _mm256_castps_pd(_mm256_unpacklo_ps(Y[2], Y[3]));
                const __m256d t3 = _mm256_castps_pd(_mm256_unpackhi_ps(Y[2], Y[3]));
                const __m256 col[4] = {_mm256_castpd_ps(_mm256_unpacklo_pd(t0, t2v)),
                                       _mm256_castpd_ps(_mm256_unpackhi_pd(t0, t2v)),
                                       _mm256_castpd_ps(_mm256_unpacklo_pd(t1, t3)),
                                       _mm256_castpd_ps(_mm256_unpackhi_pd(t1, t3))};
                for (int64_t ch = 4 * k; ch < D && ch < 4 * k + 4; ++ch)
                    _mm256_store_ps(RT + ch * Kc + 8 * g, _mm256_and_ps(vm, _mm256_mul_ps(
                        _mm256_sub_ps(col[ch - 4 * k], _mm256_set1_ps(cf[ch])),
                        _mm256_set1_ps(rs[ch]))));
            }
        }
        for (int64_t g0 = 0; g0 < Gc; g0 += NG) {
            const int full = 8 * (g0 + NG) <= K;
            for (int i = 0; i < NG; ++i) {
                const int64_t left = K - 8 * (g0 + i);
                const int32_t nv = left <= 0 ? 0 : (left < 8 ? (int32_t)left : 8);
                _mm256_store_ps(VM + 8 * i, _mm256_castsi256_ps(
                    _mm256_cmpgt_epi32(_mm256_set1_epi32(nv), iota)));
            }
            for (int a = 0; a < 3; ++a) {
                const float *wa = WV + a * Kc + 8 * g0;
                for (int i = 0; i < NG; ++i)
                    _mm256_store_ps(PV + 8 * i,
                                    exp2_neg0(_mm256_mul_ps(nh2ql, _mm256_load_ps(wa + 8 * i))));
                for (int64_t m = 0; m < lp->nblk; ++m) {
                    const __m256 bm = _mm256_set1_ps(lp->b[m]);
                    const int64_t L = nc - m * lp->B < lp->B ? nc - m * lp->B : lp->B;
                    __m256 U[NG];
                    for (int i = 0; i < NG; ++i) {
                        const __m256 u = _mm256_sub_ps(bm, _mm256_load_ps(wa + 8 * i));
                        U[i] = _mm256_and_ps(_mm256_load_ps(VM + 8 * i),
                                             exp2_neg0(_mm256_mul_ps(_mm256_mul_ps(u, u), ql)));
                    }
                    for (int64_t l = 0; l < L; ++l) {
                        const int64_t ch = a * nc + m * lp->B + l;
                        __m256 mx = ninf, sm = zero;
                        if (ch < D) {
                            const float *rt = RT + ch * Kc + 8 * g0;
#define PGN_ROW(i) _mm256_load_ps(rt + 8 * (i))
                            if (full) { PGN_CHANNEL(1, PGN_ROW) }
                            else { PGN_CHANNEL(0, PGN_ROW) }
#undef PGN_ROW
                        } else {
                            const __m256 gv = _mm256_set1_ps(cf[ch - D] * ct[ch]);
#define PGN_CENTRE(i) gv
                            if (full) { PGN_CHANNEL(1, PGN_CENTRE) }
                            else { PGN_CHANNEL(0, PGN_CENTRE) }
#undef PGN_CENTRE
                        }
                        if (g0) {  /* past 64 neighbours: the chunks ahead's partials */
                            mx = _mm256_max_ps(mx, _mm256_load_ps(MX + ch * 8));
                            sm = _mm256_add_ps(sm, _mm256_load_ps(SM + ch * 8));
                        }
                        _mm256_store_ps(MX + ch * 8, mx);
                        _mm256_store_ps(SM + ch * 8, sm);
                    }
                }
            }
        }
        float *o = out + c * D2p;
        const __m256 ik = _mm256_set1_ps(invk);
        for (int64_t h = 0; h < D2; h += 8)
            _mm256_store_ps(acc + h, _mm256_mul_ps(_mm256_load_ps(t2 + h), _mm256_fmadd_ps(
                red8_add(SM + h * 8), ik, red8_max(MX + h * 8))));
        for (int64_t ch = 0; ch < D2; ++ch) o[ch] = acc[ch];
        for (int64_t d = D2; d < D2p; ++d) o[d] = 0.0f;
    }
}
#undef PGN_CHANNEL
#undef NG
#endif

/* ISO C wants a non-empty translation unit when AVX2 is off */
typedef int pgn_avx2_lanes_unit;
