/* Stage 1 (16 < D <= 32) with neighbours in the lanes, AVX2 + FMA:
 * pgn_avx512_neighbour_lanes.c with 8-float lanes, for CPUs without AVX-512 (PGN_AVX2). An axis's Gaussians are running
 * products U_{l+1} = U_l P from U_0 = A (2 exponentials per axis and 8 neighbours, one
 * block at the default sigma), T folded out of the products and back in on the results;
 * the offset half's rows computed from the points on the initial embedding (init_rows8),
 * else transposed per centre, 4 channels at a time. Sixteen ymm registers
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


/* The initial Gaussians of ng (1 or 2) groups of 8 neighbours (PGN_INIT_ROWS_BODY,
 * pgn_common.h; vm[i]: group i's valid-lane mask): not inlined, its file built with
 * -ffp-contract=off, so a neighbour on its centre's point gives an offset of exactly 0. */
__attribute__((noinline)) static void init_rows8(const __m256 *w, int ng, const lanes_t *lp,
                                                 const float *csub, const __m256 *vm,
                                                 float *out, int64_t stride) {
#define PGN_ROW_STORE(p, m, U, c) \
    _mm256_store_ps((p), _mm256_and_ps((m), _mm256_sub_ps((U), _mm256_set1_ps(c))))
    PGN_INIT_ROWS_BODY(__m256, 8, 6, exp2_neg0, _mm256_set1_ps, _mm256_sub_ps, _mm256_mul_ps,
                       PGN_ROW_STORE);
#undef PGN_ROW_STORE
}

/* One channel over a chunk's NG groups: w = (f + U) U into mx (valid lanes only unless
 * FULL) and sm; U steps to U P. FU(i): f + U, f the offset (a row times the channel's
 * factor, by a multiply-add) or the centre value of group i. */
#define PGN_CHANNEL(FULL, FU)                                                            \
    for (int i = 0; i < NG; ++i) {                                                       \
        const __m256 w = _mm256_mul_ps(FU(i), U[i]);                                     \
        U[i] = _mm256_mul_ps(U[i], _mm256_load_ps(PV + 8 * i));                          \
        mx = _mm256_max_ps(mx, FULL ? w                                                  \
                                    : _mm256_blendv_ps(ninf, w, _mm256_load_ps(VM + 8 * i))); \
        sm = _mm256_add_ps(sm, w);                                                       \
    }

/* As pgn_aggregate_neighbour_lanes_avx512; scr: pgn_lanes_scratch(K) floats, 64-byte aligned. */
void pgn_aggregate_neighbour_lanes_avx2(const float *feat, int64_t D, const int64_t *cidx,
                              const int32_t *nb, int64_t S, int64_t K, const float *vx,
                              float r, const lanes_t *lp, const lanes_init_t *ini,
                              float *out, float *scr) {
    const int64_t Dp = padded(D), D2 = 2 * D, D2p = padded(D2), nc = lp->nc;
    const int64_t G = (K + 7) / 8, Kc = (K + 8 * NG - 1) / (8 * NG) * (8 * NG), Gc = Kc / 8;
    float *RT = scr;            /* (D, Kc): row - cf by channel, 0 past K (times sc below) */
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
    /* as pgn_avx512_neighbour_lanes.c: the rows' factor sc (T0 rs where ini), a centre's own U */
    float sc[64], zero1[64], cu[32 * 8] __attribute__((aligned(32))), cuj[32];
    const int64_t n0 = ini ? ini->lp->nc : 0;
    for (int64_t ch = 0; ch < 64; ++ch) {
        sc[ch] = ch < 3 * n0 ? ini->lp->T[ch % n0] * rs[ch] : rs[ch];
        zero1[ch] = 0.0f;
    }
    const float rx = ini ? ini->rx : 1.0f;
    const __m256 vW = _mm256_set1_ps(W), vnW = _mm256_set1_ps(-W);
    memset(RT, 0, sizeof(float) * (size_t)((D + 3) * Kc));
    for (int64_t c = 0; c < S; ++c) {
        const float *cf = feat + cidx[c] * Dp;
        const int32_t *nr = nb + c * K;
        const float *vc = vx + c * K * 3;
        if (ini) {
            /* vc: the neighbours' points; their offsets as the other paths, and their rows
             * from the points two groups at a time */
            const float *pc = ini->pts + cidx[c] * 3;
            const __m256 vrx = _mm256_set1_ps(rx);
            __m256 w[6], vm[2];
            for (int a = 0; a < 3; ++a)
                w[a] = _mm256_min_ps(_mm256_max_ps(_mm256_set1_ps(pc[a]), vnW), vW);
            vm[0] = _mm256_castsi256_ps(_mm256_set1_epi32(-1));
            init_rows8(w, 1, ini->lp, zero1, vm, cu, 8);
            for (int64_t j = 0; j < 3 * n0; ++j) cuj[j] = cu[8 * j];
            for (int64_t g = 0; g < G; ++g) {
                const int64_t nv = K - 8 * g < 8 ? K - 8 * g : 8;
                const int i = (int)(g & 1);
                vm[i] = _mm256_castsi256_ps(
                    _mm256_cmpgt_epi32(_mm256_set1_epi32((int32_t)nv), iota));
                /* 8 points' 24 floats (the last group's through a padded copy) by axis:
                 * two blends and a permute an axis */
                __m256 A, Bv, C;
                if (nv == 8) {
                    const float *p8 = vc + 24 * g;
                    A = _mm256_loadu_ps(p8); Bv = _mm256_loadu_ps(p8 + 8);
                    C = _mm256_loadu_ps(p8 + 16);
                } else {
                    float tmp[24] = {0};
                    memcpy(tmp, vc + 24 * g, sizeof(float) * (size_t)(3 * nv));
                    A = _mm256_loadu_ps(tmp); Bv = _mm256_loadu_ps(tmp + 8);
                    C = _mm256_loadu_ps(tmp + 16);
                }
                const __m256 px = _mm256_permutevar8x32_ps(_mm256_blend_ps(_mm256_blend_ps(
                    A, Bv, 0x92), C, 0x24), _mm256_setr_epi32(0, 3, 6, 1, 4, 7, 2, 5));
                const __m256 py = _mm256_permutevar8x32_ps(_mm256_blend_ps(_mm256_blend_ps(
                    A, Bv, 0x24), C, 0x49), _mm256_setr_epi32(1, 4, 7, 2, 5, 0, 3, 6));
                const __m256 pz = _mm256_permutevar8x32_ps(_mm256_blend_ps(_mm256_blend_ps(
                    A, Bv, 0x49), C, 0x92), _mm256_setr_epi32(2, 5, 0, 3, 6, 1, 4, 7));
                const __m256 pa[3] = {px, py, pz};
                for (int a = 0; a < 3; ++a) {
                    w[3 * i + a] = _mm256_min_ps(_mm256_max_ps(pa[a], vnW), vW);
                    const __m256 v = _mm256_mul_ps(_mm256_sub_ps(pa[a], _mm256_set1_ps(pc[a])), vrx);
                    _mm256_store_ps(WV + a * Kc + 8 * g, _mm256_and_ps(
                        vm[i], _mm256_min_ps(_mm256_max_ps(v, vnW), vW)));
                }
                if (i == 1 || g == G - 1)
                    init_rows8(w, i + 1, ini->lp, cuj, vm, RT + 8 * (g - i), Kc);
            }
        } else {
            for (int64_t t = 0; t < K; ++t)
                for (int a = 0; a < 3; ++a) {
                    const float v = vc[3 * t + a];
                    WV[a * Kc + t] = v < -W ? -W : (v > W ? W : v);
                }
        }
        /* rows by channel, 4 channels at a time: 128-bit half h of Y[m] holds row 4 h + m,
         * then a 4 x 4 transpose in each half */
        for (int64_t g = 0; g < G && !ini; ++g) {
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
                    _mm256_store_ps(RT + ch * Kc + 8 * g, _mm256_and_ps(
                        vm, _mm256_sub_ps(col[ch - 4 * k], _mm256_set1_ps(cf[ch]))));
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
                            const __m256 f = _mm256_set1_ps(sc[ch]);
#define PGN_ROW(i) _mm256_fmadd_ps(_mm256_load_ps(rt + 8 * (i)), f, U[i])
                            if (full) { PGN_CHANNEL(1, PGN_ROW) }
                            else { PGN_CHANNEL(0, PGN_ROW) }
#undef PGN_ROW
                        } else if (ini) {
                            /* as pgn_avx512_neighbour_lanes.c: w grows with U here (g, U >= 0) */
                            const __m256 gv = _mm256_set1_ps(cf[ch - D] * ct[ch]);
                            __m256 s2 = zero;
                            mx = zero;
                            for (int i = 0; i < NG; ++i) {
                                mx = _mm256_max_ps(mx, U[i]);
                                sm = _mm256_add_ps(sm, U[i]);
                                s2 = _mm256_fmadd_ps(U[i], U[i], s2);
                                U[i] = _mm256_mul_ps(U[i], _mm256_load_ps(PV + 8 * i));
                            }
                            mx = _mm256_mul_ps(_mm256_add_ps(gv, mx), mx);
                            sm = _mm256_fmadd_ps(gv, sm, s2);
                        } else {
                            const __m256 gv = _mm256_set1_ps(cf[ch - D] * ct[ch]);
#define PGN_CENTRE(i) _mm256_add_ps(gv, U[i])
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
                pgn_red8_add(SM + h * 8), ik, pgn_red8_max(MX + h * 8))));
        for (int64_t ch = 0; ch < D2; ++ch) o[ch] = acc[ch];
        for (int64_t d = D2; d < D2p; ++d) o[d] = 0.0f;
    }
}
#undef PGN_CHANNEL
#undef NG
#endif

/* ISO C wants a non-empty translation unit when AVX2 is off */
typedef int pgn_avx2_lanes_unit;
