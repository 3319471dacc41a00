/* Stage aggregation with neighbours in the lanes (AVX-512), for 16 < D <= 32: stage 1 of
 * the default encoder (D = 27: 54 pe channels, 18 Gaussians per axis).
 *
 * pgn_aggregate_narrow_avx512 puts channels in the lanes and evaluates every Gaussian with its
 * own exponential: 4 vectors of exp a neighbour. Here the 16 lanes are 16 neighbours of one
 * centre and each axis's channels are walked along its grid of centres b_0 + j h. In a
 * block starting at b_m, pe_l = T_l U_l with U_l = A_m P^l, A_m = exp(q (b_m - w)^2),
 * P = exp(-2 q h w) (w: the neighbour's offset on that axis) and T_l = exp(2 q l h b_m +
 * q l^2 h^2): the separable form of sep_t, the powers taken one step at a time. An axis
 * then costs 2 exponentials per 16 neighbours (one block) instead of one per channel.
 * pgn_lanes_plan (pgn_stage_plan.c) picks the blocks (lanes_range_ok).
 *
 * The offset half needs the neighbours' feature rows by channel, in a channel-major table
 * per centre. On the initial embedding (lanes_init_t: stage 1 of the encoder) a row is the
 * Gaussians of the neighbour's own coordinates, so its offsets are computed in the lanes
 * by the same chain (init_rows); elsewhere the rows are read and transposed. Each
 * channel's max and sum are kept per lane and
 * reduced over the lanes at the end of the centre. Features stay within a few 1e-6 of the
 * oracle; a result depends on its centre only, so batches, threads and the helper's
 * chunks stay bit-identical.
 */
#include "pgn_common.h"

#if defined(__AVX512F__)
/* 16 channels' lane partials V (16, 16) reduced over the lanes: lane c of the result is
 * channel c's max (MAX) or sum. In 256-bit operations (half the cost of 512-bit ones on
 * Zen 4): each channel's two halves
 * combined, then pgn_red8 per 8 channels, the two results joined. */
#define PGN_RED16(NAME, OP, RED8)                                                        \
    static inline __m512 NAME(const float *V) {                                         \
        float hv[128] __attribute__((aligned(32)));                                      \
        for (int c = 0; c < 16; ++c)                                                     \
            _mm256_store_ps(hv + 8 * c, OP(_mm256_load_ps(V + 16 * c),                   \
                                           _mm256_load_ps(V + 16 * c + 8)));             \
        return _mm512_castpd_ps(_mm512_insertf64x4(                                      \
            _mm512_castpd256_pd512(_mm256_castps_pd(RED8(hv))),                          \
            _mm256_castps_pd(RED8(hv + 64)), 1));                                        \
    }
PGN_RED16(red16_max, _mm256_max_ps, pgn_red8_max)
PGN_RED16(red16_add, _mm256_add_ps, pgn_red8_add)
#undef PGN_RED16

#define NG 8  /* groups of 16 neighbours held in registers: 128 neighbours a chunk */

#define IRG 4  /* groups of neighbours an init_rows call (2: slower; 8: spills) */
/* The initial Gaussians of ng (1 to IRG) groups of 16 neighbours (PGN_INIT_ROWS_BODY,
 * pgn_common.h). Not inlined, and its file built with -ffp-contract=off: a centre (csub 0)
 * and its neighbours then take the same operations, so a neighbour on the centre's point
 * gives the centre's U bit for bit and an offset of exactly 0, as the rows' table does. */
__attribute__((noinline)) static void init_rows(const __m512 *w, int ng, const lanes_t *lp,
                                                const float *csub, const __mmask16 *vm,
                                                float *out, int64_t stride) {
#define PGN_ROW_STORE(p, m, U, c) \
    _mm512_store_ps((p), _mm512_maskz_sub_ps((m), (U), _mm512_set1_ps(c)))
    PGN_INIT_ROWS_BODY(__m512, 16, 3 * IRG, exp2_neg_avx512, _mm512_set1_ps, _mm512_sub_ps,
                       _mm512_mul_ps, PGN_ROW_STORE);
#undef PGN_ROW_STORE
}

void pgn_aggregate_neighbour_lanes_avx512(const float *feat, int64_t D, const int64_t *cidx,
                                const int32_t *nb, int64_t S, int64_t K, const float *vx,
                                float r, const lanes_t *lp, const lanes_init_t *ini,
                                float *out, float *scr) {
    const int64_t Dp = padded(D), D2 = 2 * D, D2p = padded(D2), nc = lp->nc;
    const int64_t G = (K + 15) / 16, Kc = (K + 16 * NG - 1) / (16 * NG) * (16 * NG);
    const int64_t Gc = Kc / 16;
    float *RT = scr;            /* (D, Kc): row - cf by channel, 0 past K (times rs below) */
    float *WV = RT + D * Kc;    /* (3, Kc): clamped offsets by axis */
    float *MX = WV + 3 * Kc;    /* (2D, 16): per-lane max of each channel */
    float *SM = MX + 64 * 16;   /* (2D, 16): per-lane sum, then 64 floats of results */
    const float invk = 1.0f / (float)K;
    /* T folded out (pgn_lanes_scales): one multiply a step less */
    float *rs = SM + 64 * 16 + 64, *ct = rs + 64, *t2 = ct + 64;
    pgn_lanes_scales(lp, D2, r, rs, ct, t2);
    const __m512 vW = _mm512_set1_ps(lp->W);
    const __m512 vnW = _mm512_set1_ps(-lp->W), zero = _mm512_setzero_ps();
    const __m512 ql = _mm512_set1_ps(lp->ql), nh2ql = _mm512_set1_ps(-lp->h2ql);
    /* axis a of neighbour i is float 3 i + a of the group's 48: two permutes */
    __m512i ia[3];
    __mmask16 hi[3];
    for (int a = 0; a < 3; ++a) {
        int32_t t[16];
        hi[a] = 0;
        for (int i = 0; i < 16; ++i) {
            t[i] = (3 * i + a) & 31;
            if (3 * i + a >= 32) hi[a] |= (__mmask16)(1u << i);
        }
        ia[a] = _mm512_loadu_si512((const void *)t);
    }
    /* ini: a row's offset e_j = (U_j - U_j(centre)) T0_j (T0: the initial Gaussians' T),
     * so its factor is T0 rs instead of rs; zero1: a centre's own U */
    float sc[64] __attribute__((aligned(64))), zero1[64];
    float cu[32 * 16] __attribute__((aligned(64))), cuj[32];
    const int64_t n0 = ini ? ini->lp->nc : 0;
    for (int64_t ch = 0; ch < 64; ++ch) {
        sc[ch] = ch < 3 * n0 ? ini->lp->T[ch % n0] * rs[ch] : rs[ch];
        zero1[ch] = 0.0f;
    }
    const __m512 vrx = _mm512_set1_ps(ini ? ini->rx : 1.0f);
    /* neighbours past K stay 0 in both tables (WV follows RT) */
    memset(RT, 0, sizeof(float) * (size_t)((D + 3) * Kc));
    for (int64_t c = 0; c < S; ++c) {
        const float *cf = feat + cidx[c] * Dp;
        const int32_t *nr = nb + c * K;
        const float *vc = vx + c * K * 3;
        __m512 pc[3] = {zero, zero, zero};
        if (ini) {
            __m512 w[3];
            for (int a = 0; a < 3; ++a) {
                pc[a] = _mm512_set1_ps(ini->pts[cidx[c] * 3 + a]);
                w[a] = _mm512_min_ps(_mm512_max_ps(pc[a], vnW), vW);
            }
            const __mmask16 all = 0xffff;
            init_rows(w, 1, ini->lp, zero1, &all, cu, 16);
            for (int64_t j = 0; j < 3 * n0; ++j) cuj[j] = cu[16 * j];
        }
        /* the offsets by axis and the neighbours' rows by channel, 16 neighbours a step */
        __m512 wg[3 * IRG];
        __mmask16 vmg[IRG];
        for (int64_t g = 0; g < G; ++g) {
            const int64_t nv = K - 16 * g < 16 ? K - 16 * g : 16, nf = 3 * nv;
            const __mmask16 vm = (__mmask16)((1u << nv) - 1u);
            const __mmask16 m0 = nf >= 16 ? 0xffff : (__mmask16)((1u << nf) - 1u);
            const __mmask16 m1 = nf >= 32 ? 0xffff
                                 : (nf <= 16 ? 0 : (__mmask16)((1u << (nf - 16)) - 1u));
            const __mmask16 m2 = nf >= 48 ? 0xffff
                                 : (nf <= 32 ? 0 : (__mmask16)((1u << (nf - 32)) - 1u));
            const __m512 x0 = _mm512_maskz_loadu_ps(m0, vc + 48 * g);
            const __m512 x1 = _mm512_maskz_loadu_ps(m1, vc + 48 * g + 16);
            const __m512 x2 = _mm512_maskz_loadu_ps(m2, vc + 48 * g + 32);
            __m512 *w = wg + 3 * (g % IRG);
            for (int a = 0; a < 3; ++a) {
                __m512 v = _mm512_permutex2var_ps(x0, ia[a], x1);
                v = _mm512_mask_permutexvar_ps(v, hi[a], ia[a], x2);
                if (ini) {  /* v: the neighbours' points; their offsets as the other paths */
                    w[a] = _mm512_min_ps(_mm512_max_ps(v, vnW), vW);
                    v = _mm512_mul_ps(_mm512_sub_ps(v, pc[a]), vrx);
                }
                v = _mm512_maskz_mov_ps(vm, _mm512_min_ps(_mm512_max_ps(v, vnW), vW));
                _mm512_store_ps(WV + a * Kc + 16 * g, v);
            }
            if (ini) {  /* the rows IRG groups at a time */
                const int64_t gi = g % IRG;
                vmg[gi] = vm;
                if (gi == IRG - 1 || g == G - 1)
                    init_rows(wg, (int)gi + 1, ini->lp, cuj, vmg, RT + 16 * (g - gi), Kc);
                continue;
            }
            /* rows by channel, 4 channels at a time: 128-bit lane j of Y[m] holds row 4 j + m
             * (two 256-bit pairs of loads and one insert; broadcasts merged under masks took
             * 0.02 ms a cloud more), then a 4 x 4 transpose in each lane */
            const float *rows[16];
            for (int i = 0; i < 16; ++i)
                rows[i] = feat + (int64_t)nr[16 * g + (i < nv ? i : 0)] * Dp;
            for (int64_t k = 0; 4 * k < D; ++k) {
                __m512 Y[4];
                for (int m = 0; m < 4; ++m) {
                    const __m256 lo = _mm256_insertf128_ps(
                        _mm256_castps128_ps256(_mm_load_ps(rows[m] + 4 * k)),
                        _mm_load_ps(rows[4 + m] + 4 * k), 1);
                    const __m256 hi = _mm256_insertf128_ps(
                        _mm256_castps128_ps256(_mm_load_ps(rows[8 + m] + 4 * k)),
                        _mm_load_ps(rows[12 + m] + 4 * k), 1);
                    Y[m] = _mm512_castpd_ps(_mm512_insertf64x4(_mm512_castpd256_pd512(
                        _mm256_castps_pd(lo)), _mm256_castps_pd(hi), 1));
                }
                const __m512d t0 = _mm512_castps_pd(_mm512_unpacklo_ps(Y[0], Y[1]));
                const __m512d t1 = _mm512_castps_pd(_mm512_unpackhi_ps(Y[0], Y[1]));
                const __m512d t2v = _mm512_castps_pd(_mm512_unpacklo_ps(Y[2], Y[3]));
                const __m512d t3 = _mm512_castps_pd(_mm512_unpackhi_ps(Y[2], Y[3]));
                const __m512 col[4] = {_mm512_castpd_ps(_mm512_unpacklo_pd(t0, t2v)),
                                       _mm512_castpd_ps(_mm512_unpackhi_pd(t0, t2v)),
                                       _mm512_castpd_ps(_mm512_unpacklo_pd(t1, t3)),
                                       _mm512_castpd_ps(_mm512_unpackhi_pd(t1, t3))};
                for (int64_t ch = 4 * k; ch < D && ch < 4 * k + 4; ++ch)
                    _mm512_store_ps(RT + ch * Kc + 16 * g, _mm512_maskz_sub_ps(
                        vm, col[ch - 4 * k], _mm512_set1_ps(cf[ch])));
            }
        }
        for (int64_t g0 = 0; g0 < Gc; g0 += NG) {
            __mmask16 vm[NG];
            for (int i = 0; i < NG; ++i) {
                const int64_t t0 = 16 * (g0 + i);
                const int64_t nv = K - t0 <= 0 ? 0 : (K - t0 < 16 ? K - t0 : 16);
                vm[i] = (__mmask16)((1u << nv) - 1u);
            }
            /* only the chunk's last group short (K = 120: 8 of its 16 lanes): the other
             * groups' max unmasked (a masked max also costs a register copy) */
            int head_full = 1;
            for (int i = 0; i < NG - 1; ++i) head_full &= vm[i] == 0xffff;
            for (int a = 0; a < 3; ++a) {
                const float *wa = WV + a * Kc + 16 * g0;
                __m512 P[NG], U[NG];
                for (int i = 0; i < NG; ++i)
                    P[i] = exp2_neg_avx512(_mm512_mul_ps(nh2ql, _mm512_load_ps(wa + 16 * i)));
                for (int64_t m = 0; m < lp->nblk; ++m) {
                    const __m512 bm = _mm512_set1_ps(lp->b[m]);
                    const int64_t L = nc - m * lp->B < lp->B ? nc - m * lp->B : lp->B;
                    for (int i = 0; i < NG; ++i) {
                        const __m512 u = _mm512_sub_ps(bm, _mm512_load_ps(wa + 16 * i));
                        U[i] = _mm512_maskz_mov_ps(
                            vm[i], exp2_neg_avx512(_mm512_mul_ps(_mm512_mul_ps(u, u), ql)));
                    }
                    for (int64_t l = 0; l < L; ++l) {
                        const int64_t ch = a * nc + m * lp->B + l;
                        __m512 mx = _mm512_set1_ps(-INFINITY), sm = zero;
/* one channel over the chunk's groups: w = (f + U) U, FU = f + U with f from RT times
 * the channel's factor (offset half; a multiply-add where the centre half adds, which
 * evens the block's multiply and add slots) or the centre's g (centre half); FULL: groups
 * before the last have no padding lanes */
#define PGN_CHANNEL(FULL, FU)                                                              \
    for (int i = 0; i < NG; ++i) {                                                         \
        const __m512 w = _mm512_mul_ps((FU), U[i]);                                        \
        U[i] = _mm512_mul_ps(U[i], P[i]);                                                  \
        mx = (FULL) && i < NG - 1 ? _mm512_max_ps(mx, w)                                   \
                                  : _mm512_mask_max_ps(mx, vm[i], mx, w);                  \
        sm = _mm512_add_ps(sm, w);                                                         \
    }
                        if (ch < D) {
                            const float *rt = RT + ch * Kc + 16 * g0;
                            const __m512 f = _mm512_set1_ps(sc[ch]);
                            if (head_full) {
                                PGN_CHANNEL(1, _mm512_fmadd_ps(_mm512_load_ps(rt + 16 * i), f, U[i]))
                            } else {
                                PGN_CHANNEL(0, _mm512_fmadd_ps(_mm512_load_ps(rt + 16 * i), f, U[i]))
                            }
                        } else if (ini) {
                            /* the initial embedding's centre half: g >= 0 and U >= 0, so
                             * w = (g + U) U grows with U (and rounding keeps the order): a
                             * lane's max is w at its largest U, its sum g sum(U) + sum(U^2) */
                            const __m512 g = _mm512_set1_ps(cf[ch - D] * ct[ch]);
                            __m512 s2 = zero;
                            mx = zero;
                            for (int i = 0; i < NG; ++i) {
                                mx = _mm512_max_ps(mx, U[i]);
                                sm = _mm512_add_ps(sm, U[i]);
                                s2 = _mm512_fmadd_ps(U[i], U[i], s2);
                                U[i] = _mm512_mul_ps(U[i], P[i]);
                            }
                            mx = _mm512_mul_ps(_mm512_add_ps(g, mx), mx);
                            sm = _mm512_fmadd_ps(g, sm, s2);
                        } else {
                            const __m512 g = _mm512_set1_ps(cf[ch - D] * ct[ch]);
                            if (head_full) {
                                PGN_CHANNEL(1, _mm512_add_ps(g, U[i]))
                            } else {
                                PGN_CHANNEL(0, _mm512_add_ps(g, U[i]))
                            }
                        }
#undef PGN_CHANNEL
                        if (g0) {  /* past 128 neighbours: the chunks ahead's partials */
                            mx = _mm512_max_ps(mx, _mm512_load_ps(MX + ch * 16));
                            sm = _mm512_add_ps(sm, _mm512_load_ps(SM + ch * 16));
                        }
                        _mm512_store_ps(MX + ch * 16, mx);
                        _mm512_store_ps(SM + ch * 16, sm);
                    }
                }
            }
        }
        /* lanes reduced into the 64 floats past SM (the caller applies gelu) */
        float *o = out + c * D2p, *acc = SM + 64 * 16;
        const __m512 ik = _mm512_set1_ps(invk);
        for (int64_t h = 0; h < D2; h += 16)
            _mm512_store_ps(acc + h, _mm512_mul_ps(_mm512_load_ps(t2 + h), _mm512_fmadd_ps(
                red16_add(SM + h * 16), ik, red16_max(MX + h * 16))));
        for (int64_t ch = 0; ch < D2; ++ch) o[ch] = acc[ch];
        for (int64_t d = D2; d < D2p; ++d) o[d] = 0.0f;
    }
}
#undef NG
#endif
