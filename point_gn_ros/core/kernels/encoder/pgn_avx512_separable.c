/* Point-GN's separable stages (2-4 of the default encoder) with AVX-512 intrinsics: blocks
 * of 8 (sep_pass) or 16 (sep_group16, sep_centre16) Gaussians of one axis a vector, from
 * pgn_sep_prepare's factors (pgn_stage_portable.c). Only where the compiler targets AVX-512 F and
 * VL; elsewhere this file is empty (pgn_dispatch.c's table). */
#include "pgn_common.h"

#if defined(__AVX512F__) && defined(__AVX512VL__)
/* Separable stages with AVX-512: pe is never stored. The 2D pe channels are walked as
 * the (axis, block) groups of 8 of the separable form, channel a n + 8 m + l, so a
 * group's pe for neighbour t is one broadcast times a vector:
 * A[t, a, m] * (T[m, 0..8) * P[t, a]^(0..8)), the powers by masked multiplies of
 * P, P^2, P^4 (the same products as pgn_sep_prepare's E, so the same values). Channel ch
 * aggregates ((row[ch] - cf[ch]) r + pe) pe for ch < D and (cf[ch - D] + pe) pe
 * above (G holds cf[ch] / cf[ch - D]); lanes past an axis's n centres are masked off.
 * mx, sm, G: 2D + 16 floats of scratch. Blocks of 8 (sep_pass) take four neighbours a
 * pass, like pgn_stage_aggregate; blocks of 16 (sep_centre16) run each group of blocks
 * over all K neighbours with its max and sum in registers. */
static inline __attribute__((always_inline)) void sep_pass(
        const float *const *rows, int nt, int64_t t0, int64_t nta, const sep_t *fx,
        int64_t D, const float *G, float r, float *mx, float *sm) {
    const int64_t n = fx->n, M = fx->M;
    const __m256 one = _mm256_set1_ps(1.0f), vr = _mm256_set1_ps(r);
    for (int a = 0; a < 3; ++a) {
        __m256 e[4];
        for (int i = 0; i < nt; ++i) {
            const int64_t ta = 3 * (t0 + i) + a;
            __m256 v = one;
            v = _mm256_mask_mul_ps(v, 0xAA, v, _mm256_set1_ps(fx->E[1 * nta + ta]));
            v = _mm256_mask_mul_ps(v, 0xCC, v, _mm256_set1_ps(fx->E[2 * nta + ta]));
            e[i] = _mm256_mask_mul_ps(v, 0xF0, v, _mm256_set1_ps(fx->E[4 * nta + ta]));
        }
        for (int64_t m = 0; m < M; ++m) {
            const int64_t ch = a * n + 8 * m;
            const int64_t nv = n - 8 * m < 8 ? n - 8 * m : 8;
            const __mmask8 valid = (__mmask8)((1u << nv) - 1u);
            const int64_t no = D - ch < 0 ? 0 : (D - ch > 8 ? 8 : D - ch);
            const __mmask8 off = (__mmask8)(((1u << no) - 1u) & valid);  /* ch + l < D */
            const __m256 T = _mm256_loadu_ps(fx->T + 8 * m);
            const __m256 g = _mm256_loadu_ps(G + ch);
            __m256 w[4];
            for (int i = 0; i < nt; ++i) {
                const __m256 am = _mm256_set1_ps(fx->A[m * nta + 3 * (t0 + i) + a]);
                const __m256 pe = _mm256_mul_ps(am, _mm256_mul_ps(T, e[i]));
                __m256 f = g;
                if (off) {
                    const __m256 row = _mm256_maskz_loadu_ps(off, rows[i] + ch);
                    f = _mm256_mask_blend_ps(off, g,
                                             _mm256_fmadd_ps(_mm256_sub_ps(row, g), vr, pe));
                    w[i] = _mm256_mul_ps(_mm256_mask_blend_ps(off, _mm256_add_ps(f, pe), f), pe);
                } else {
                    w[i] = _mm256_mul_ps(_mm256_add_ps(f, pe), pe);
                }
            }
            __m256 wm = w[0], ws = w[0];
            if (nt == 4) {
                wm = _mm256_max_ps(_mm256_max_ps(w[0], w[1]), _mm256_max_ps(w[2], w[3]));
                ws = _mm256_add_ps(_mm256_add_ps(w[0], w[1]), _mm256_add_ps(w[2], w[3]));
            }
            _mm256_mask_storeu_ps(mx + ch, valid, _mm256_max_ps(wm, _mm256_loadu_ps(mx + ch)));
            _mm256_mask_storeu_ps(sm + ch, valid, _mm256_add_ps(_mm256_loadu_ps(sm + ch), ws));
        }
    }
}

/* Blocks of 16 (one 512-bit vector a block, P^0..15 built once per neighbour and axis
 * into E16) walked in groups: a group is NB <= 4 blocks of one axis and one kind, and it
 * runs over all K neighbours with its max and sum in registers, so nothing is stored
 * until the centre's group is done. Kinds: SEP_CTR blocks are all centre channels
 * (ch >= D), SEP_OFF all offset channels, SEP_MIX the block that straddles D. */
enum { SEP_CTR, SEP_OFF, SEP_MIX };

static inline __attribute__((always_inline)) void sep_group16(
        const int kind, const int NB, const int64_t *chs, const __mmask16 *valid,
        const __mmask16 *off, const float *const *Ab, const float *E16, const float *feat,
        int64_t Dp, const int32_t *nr, int64_t K, const float *G, const float *Gs,
        const float *rT, float *mx, float *sm) {
    /* one or two blocks: two neighbours a step into two sets of chains, so that the
     * latencies overlap */
    const int U = NB <= 2 ? 2 : 1;
    __m512 vmx[2][4], vsm[2][4], pmx[2][4], g[4], gs[4], rt[4];
    for (int b = 0; b < NB; ++b) {
        for (int u = 0; u < U; ++u) {
            vmx[u][b] = kind == SEP_CTR ? _mm512_setzero_ps() : _mm512_set1_ps(-INFINITY);
            vsm[u][b] = _mm512_setzero_ps();
            pmx[u][b] = _mm512_setzero_ps();
        }
        g[b] = _mm512_loadu_ps(G + chs[b]);
        gs[b] = _mm512_loadu_ps(Gs + chs[b]);
        rt[b] = _mm512_loadu_ps(rT + chs[b]);
    }
    /* A centre block pools w = (gs + pe) pe, pe >= 0, convex in pe: its max over the
     * neighbours is w at pe's largest or smallest value, and its sum is gs sum(pe) +
     * sum(pe^2) (vmx holds sum(pe^2) there). The largest pe (ph) is a max in the loop. The
     * smallest (pl) can win only where gs < -ph: w(pl) - w(ph) = (pl - ph)(pl + ph + gs).
     * The centre's feature g >= -0.17 (a gelu) and the nearest neighbour's Gaussian is
     * mostly near 1, so that is rare, and only such blocks take a second pass for pl: a min
     * a step in every block costs more. */
#define PGN_STEP(u, t)                                                                     \
    do {                                                                                   \
        __m512 e_ = _mm512_load_ps(E16 + (t) * 16);                                        \
        __asm__("" : "+v"(e_)); /* one load, kept in a register (not one per block) */     \
        const float *row_ = feat + (int64_t)nr[t] * Dp;                                    \
        for (int b = 0; b < NB; ++b) {                                                     \
            /* pe / T: T is folded into Gs, rT and the caller's final scaling */           \
            const __m512 pe = _mm512_mul_ps(_mm512_set1_ps(Ab[b][3 * (t)]), e_);           \
            if (kind == SEP_CTR) {                                                         \
                pmx[u][b] = _mm512_max_ps(pmx[u][b], pe);                                  \
                vsm[u][b] = _mm512_add_ps(vsm[u][b], pe);                                  \
                vmx[u][b] = _mm512_fmadd_ps(pe, pe, vmx[u][b]);                            \
                continue;                                                                  \
            }                                                                              \
            /* 16 floats whole, not under off's mask (a masked load cost a cycle a step): \
             * lanes past the offset channels read padding or the next row (finite; the   \
             * buffer has 16 floats of slack) and are blended away or never stored */     \
            const __m512 rw = _mm512_loadu_ps(row_ + chs[b]);                              \
            __m512 f = _mm512_fmadd_ps(_mm512_sub_ps(rw, g[b]), rt[b], pe);                \
            if (kind == SEP_MIX) f = _mm512_mask_blend_ps(off[b], _mm512_add_ps(gs[b], pe), f); \
            const __m512 w = _mm512_mul_ps(f, pe);                                         \
            vmx[u][b] = _mm512_max_ps(vmx[u][b], w);                                       \
            vsm[u][b] = _mm512_add_ps(vsm[u][b], w);                                       \
        }                                                                                  \
    } while (0)
    int64_t t = 0;
    if (U == 2)
        for (; t + 2 <= K; t += 2) {
            PGN_STEP(0, t);
            PGN_STEP(U - 1, t + 1);
        }
    for (; t < K; ++t) PGN_STEP(0, t);
#undef PGN_STEP
    for (int b = 0; b < NB; ++b) {
        __m512 m = vmx[0][b], sv = vsm[0][b], ph = pmx[0][b];
        if (U == 2) {
            if (kind == SEP_CTR) {
                m = _mm512_add_ps(m, vmx[U - 1][b]);
                ph = _mm512_max_ps(ph, pmx[U - 1][b]);
            } else {
                m = _mm512_max_ps(m, vmx[U - 1][b]);
            }
            sv = _mm512_add_ps(sv, vsm[U - 1][b]);
        }
        if (kind == SEP_CTR) {
            __m512 pl = ph;   /* w(ph) >= w(pl) where gs >= -ph */
            if (_mm512_mask_cmp_ps_mask(valid[b], gs[b], _mm512_sub_ps(_mm512_setzero_ps(), ph),
                                        _CMP_LT_OQ)) {
                pl = _mm512_set1_ps(INFINITY);
                for (int64_t t = 0; t < K; ++t)
                    pl = _mm512_min_ps(pl, _mm512_mul_ps(_mm512_set1_ps(Ab[b][3 * t]),
                                                         _mm512_load_ps(E16 + t * 16)));
            }
            sv = _mm512_fmadd_ps(gs[b], sv, m);
            m = _mm512_max_ps(_mm512_mul_ps(_mm512_add_ps(gs[b], ph), ph),
                              _mm512_mul_ps(_mm512_add_ps(gs[b], pl), pl));
        }
        _mm512_mask_storeu_ps(mx + chs[b], valid[b], m);
        _mm512_mask_storeu_ps(sm + chs[b], valid[b], sv);
    }
}

/* One centre's 2D channels with blocks of 16, axis by axis: E16 (K, 16) scratch for the
 * axis's powers of P by neighbour; runs of blocks of one kind split into groups of at most
 * 4, as even as possible. */
static void sep_centre16(const sep_t *fx, int64_t D, const float *feat, int64_t Dp,
                         const int32_t *nr, int64_t K, float *E16, const float *G,
                         const float *Gs, const float *rT, float *mx, float *sm) {
    const int64_t n = fx->n, M = fx->M, nta = 3 * K;
    const __m256 one8 = _mm256_set1_ps(1.0f);
    for (int a = 0; a < 3; ++a) {
        /* this axis's powers, P^0..15 of each neighbour (E16 stays small in L1) */
        const float *restrict E1 = fx->E + nta, *restrict E2 = fx->E + 2 * nta;
        const float *restrict E4 = fx->E + 4 * nta, *restrict E8 = fx->E + 8 * nta;
        for (int64_t t = 0; t < K; ++t) {
            /* P^0..7 in 256 bits (half the cost of 512-bit multiplies), then the upper
             * half times P^8: the same products as four masked 512-bit steps; stored as two
             * halves (an insert into one 512-bit store cost more) */
            const int64_t ta = 3 * t + a;
            __m256 v = one8;
            v = _mm256_mask_mul_ps(v, 0xAA, v, _mm256_set1_ps(E1[ta]));
            v = _mm256_mask_mul_ps(v, 0xCC, v, _mm256_set1_ps(E2[ta]));
            v = _mm256_mask_mul_ps(v, 0xF0, v, _mm256_set1_ps(E4[ta]));
            const __m256 hi = _mm256_mul_ps(v, _mm256_set1_ps(E8[ta]));
            _mm256_store_ps(E16 + t * 16, v);
            _mm256_store_ps(E16 + t * 16 + 8, hi);
        }
        int64_t m = 0;
        while (m < M) {
            /* the run of blocks from m of m's kind */
            int kind = SEP_CTR, len = 0;
            int64_t chs[16];
            __mmask16 valid[16], off[16];
            const float *Ab[16];
            for (int64_t u = m; u < M && len < 16; ++u) {
                const int64_t ch = a * n + 16 * u;
                const int64_t nv = n - 16 * u < 16 ? n - 16 * u : 16;
                const int64_t no = D - ch < 0 ? 0 : (D - ch > 16 ? 16 : D - ch);
                const __mmask16 vm = (__mmask16)((1u << nv) - 1u);
                const __mmask16 om = (__mmask16)(((1u << no) - 1u) & vm);
                const int k = om == 0 ? SEP_CTR : (om == vm ? SEP_OFF : SEP_MIX);
                if (len && (k != kind || kind == SEP_MIX)) break;
                kind = k;
                chs[len] = ch; valid[len] = vm; off[len] = om;
                Ab[len] = fx->A + u * nta + a;
                ++len;
            }
            m += len;
            /* groups of at most 4, as even as possible (each one's chains overlap) */
            const int ng = (len + 3) / 4;
            for (int gi = 0, b0 = 0; gi < ng; ++gi) {
                const int nbk = (len - b0) / (ng - gi);
                const int64_t *c = chs + b0;
                const __mmask16 *vl = valid + b0, *of = off + b0;
                const float *const *ab = Ab + b0;
#define PGN_GROUP(KIND, NBK) \
    sep_group16(KIND, NBK, c, vl, of, ab, E16, feat, Dp, nr, K, G, Gs, rT, mx, sm)
                if (kind == SEP_MIX) PGN_GROUP(SEP_MIX, 1);
                else if (kind == SEP_OFF) {
                    switch (nbk) {
                        case 1: PGN_GROUP(SEP_OFF, 1); break;
                        case 2: PGN_GROUP(SEP_OFF, 2); break;
                        case 3: PGN_GROUP(SEP_OFF, 3); break;
                        default: PGN_GROUP(SEP_OFF, 4); break;
                    }
                } else {
                    switch (nbk) {
                        case 1: PGN_GROUP(SEP_CTR, 1); break;
                        case 2: PGN_GROUP(SEP_CTR, 2); break;
                        case 3: PGN_GROUP(SEP_CTR, 3); break;
                        default: PGN_GROUP(SEP_CTR, 4); break;
                    }
                }
#undef PGN_GROUP
                b0 += nbk;
            }
        }
    }
}

void pgn_aggregate_separable_avx512(const float *feat, int64_t D, const int64_t *cidx,
                                 const int32_t *nb, int64_t S, int64_t K, const float *vx,
                                 float r, float *out, float *mx, float *sm, float *G,
                                 float *Gs, float *rT, float *T2, sep_t *fx) {
    const int64_t Dp = padded(D), D2 = 2 * D, D2p = padded(D2), nta = 3 * K;
    const float invk = 1.0f / (float)K;
    /* E16 past E's rows 0..8, 64-byte aligned (pgn_encode.c allocates the room) */
    float *E16 = (float *)(((uintptr_t)(fx->E + 9 * nta) + 63) & ~(uintptr_t)63);
    if (fx->B == 16) {
        /* pe = T A e: w = (f + pe) pe = T^2 (f / T + A e) A e, so sep_centre16 aggregates with
         * Gs = G / T and rT = r / T, one multiply a neighbour and block less, and T^2 scales
         * the results (T > 0). T of channel a n + 16 m + l is T[m][l]; lanes past an
         * axis's n centres are masked off, so their T is 1. */
        for (int64_t d = 0, j = 0; d < D2 + 32; ++d, j = j + 1 == fx->n ? 0 : j + 1) {
            const float T = d < D2 ? fx->T[j] : 1.0f;
            rT[d] = r / T;
            T2[d] = T * T;
        }
    }
    for (int64_t c = 0; c < S; ++c) {
        const float *cf = feat + cidx[c] * Dp;
        const int32_t *nr = nb + c * K;
        for (int64_t d = 0; d < D; ++d) { G[d] = cf[d]; G[D + d] = cf[d]; }
        for (int64_t d = D2; d < D2 + 32; ++d) G[d] = 0.0f;
        if (fx->B == 16)
            for (int64_t d = 0; d < D2 + 32; ++d) Gs[d] = G[d] * rT[d] / r;
        pgn_sep_prepare(fx, vx + c * K * 3, K);
        if (fx->B == 16) {  /* every group stores its channels' max and sum once */
            sep_centre16(fx, D, feat, Dp, nr, K, E16, G, Gs, rT, mx, sm);
        } else {            /* the passes update them */
            for (int64_t d = 0; d < D2 + 32; ++d) { mx[d] = -INFINITY; sm[d] = 0.0f; }
            int64_t t = 0;
            for (; t + 4 <= K; t += 4) {
                const float *rows[4] = {feat + (int64_t)nr[t] * Dp, feat + (int64_t)nr[t + 1] * Dp,
                                        feat + (int64_t)nr[t + 2] * Dp,
                                        feat + (int64_t)nr[t + 3] * Dp};
                sep_pass(rows, 4, t, nta, fx, D, G, r, mx, sm);
            }
            for (; t < K; ++t) {
                const float *rows[1] = {feat + (int64_t)nr[t] * Dp};
                sep_pass(rows, 1, t, nta, fx, D, G, r, mx, sm);
            }
        }
        float *o = out + c * D2p;
        if (fx->B == 16)
            for (int64_t d = 0; d < D2; ++d) o[d] = T2[d] * (mx[d] + sm[d] * invk);
        else
            for (int64_t d = 0; d < D2; ++d) o[d] = mx[d] + sm[d] * invk;
        for (int64_t d = D2; d < D2p; ++d) o[d] = 0.0f;
    }
}
#endif

/* ISO C wants a non-empty translation unit when AVX-512 is off */
typedef int pgn_avx512_sep_unit;
