/* Point-GN stage kernels with AVX2 + FMA intrinsics, for CPUs without AVX-512 (Intel
 * client parts, AMD before Zen 4): the loops of pgn_avx512.c with 8-float lanes. Compiled
 * only where the compiler targets AVX2 and FMA but not AVX-512 (PGN_AVX2, pgn_common.h);
 * elsewhere this file is empty and pgn_encode.c uses the AVX-512 or portable kernels. */
#include "pgn_common.h"

#if defined(PGN_AVX2)
/* Stage aggregation for 16 < D <= 32 (stage 1 of the default encoder, D = 27), as
 * pgn_aggregate_d32_avx512: lanes [0, 32) are pe channels [0, 32) (offset half), lanes
 * [32, 64) pe channels [D, D + 32) (centre half); Gaussians as 2^-(u s)^2. Sixteen ymm
 * registers do not hold both halves' 16 accumulators and 8 Gaussian vectors, so each half
 * walks the K neighbours on its own (4 vectors, 8 accumulators in registers).
 * ccs: (64,) pe-lane centres times s; lane_axis: (64,) axis of each lane; acc: 64 floats;
 * vx: (S, K, 3) plus one readable float after the last offset. */
void pgn_aggregate_d32_avx2(const float *feat, int64_t D, const int64_t *cidx,
                            const int32_t *nb, int64_t S, int64_t K, const float *vx,
                            float r, const float *ccs, const int32_t *lane_axis, float s,
                            float *out, float *acc) {
    const int64_t Dp = 32, D2p = padded(2 * D);
    const __m256 vr = _mm256_set1_ps(r);
    const __m128 s4 = _mm_set1_ps(s);
    __m256 cc[8];
    __m256i axi[8];  /* lane -> axis: one permute picks each lane's offset */
    for (int i = 0; i < 8; ++i) {
        axi[i] = _mm256_loadu_si256((const __m256i *)(lane_axis + 8 * i));
        cc[i] = _mm256_loadu_ps(ccs + 8 * i);
    }
    const float invk = 1.0f / (float)K;
    for (int64_t c = 0; c < S; ++c) {
        const float *cf = feat + cidx[c] * Dp;
        const int32_t *nr = nb + c * K;
        const float *vc = vx + c * K * 3;
        for (int h = 0; h < 2; ++h) {
            __m256 g[4], mx[4], sm[4];
            for (int j = 0; j < 4; ++j) {
                g[j] = _mm256_load_ps(cf + 8 * j);
                mx[j] = _mm256_set1_ps(-INFINITY);
                sm[j] = _mm256_setzero_ps();
            }
            for (int64_t t = 0; t < K; ++t) {
                /* offsets x, y, z (and one float more: vx has slack) times s */
                const __m256 vv = _mm256_castps128_ps256(_mm_mul_ps(_mm_loadu_ps(vc + t * 3), s4));
                const float *row = feat + (int64_t)nr[t] * Dp;
                for (int j = 0; j < 4; ++j) {
                    const int i = 4 * h + j;
                    const __m256 va = _mm256_permutevar8x32_ps(vv, axi[i]);
                    const __m256 u = _mm256_sub_ps(cc[i], va);
                    const __m256 pe = exp2_neg_avx2(_mm256_mul_ps(u, u));
                    /* offset half: (row - cf) r; centre half: cf */
                    const __m256 f = h == 0
                        ? _mm256_mul_ps(_mm256_sub_ps(_mm256_load_ps(row + 8 * j), g[j]), vr)
                        : g[j];
                    const __m256 w = _mm256_mul_ps(_mm256_add_ps(f, pe), pe);
                    mx[j] = _mm256_max_ps(mx[j], w);
                    sm[j] = _mm256_add_ps(sm[j], w);
                }
            }
            const __m256 ik = _mm256_set1_ps(invk);
            for (int j = 0; j < 4; ++j)
                _mm256_storeu_ps(acc + 32 * h + 8 * j, _mm256_fmadd_ps(sm[j], ik, mx[j]));
        }
        float *o = out + c * D2p;
        for (int64_t d = 0; d < D; ++d) o[d] = gelu(acc[d]);
        for (int64_t d = 0; d < D; ++d) o[D + d] = gelu(acc[32 + d]);
        for (int64_t d = 2 * D; d < D2p; ++d) o[d] = 0.0f;
    }
}

/* Stage 1 with half the exps (8 < n <= 18 centres per axis, n even: D = 18..27), the
 * arithmetic per pe element of pgn_aggregate_d32_avx2 in axis-aligned vectors: per
 * neighbour and axis a, the Gaussians of centres 8..15 (B_a) by 2^-t; those of centres
 * 0..7 (L_a) and 16, 17 (T) as B_a * K * R, since for a centre c' = c -+ 8h
 * 2^-(s c' - v)^2 = 2^-(s c - v)^2 * 2^((s c)^2 - (s c')^2) * 2^(+-2 mu v) (v = s w,
 * mu = s 8h): one vector exp gives R = 2^(+-2 mu v_a) for all three axes, so 4 exps a
 * neighbour instead of 8. B_a is exactly 0 where t > 125 (then its derived Gaussians are
 * below 1e-26), R is 0 below 2^-125 and at most 2^126.
 * Vectors: v = 0..2 L_a, 3..5 B_a, 6 T (n = 18 only: lanes (a, 16 + i) at 2a + i).
 * The feature plus pe of a lane is (row[ch] - cf[ch]) r + pe (ch < D, lanes at st_v + l)
 * or cf[ch - D] + pe: fma(row - cf, Rv, Cv + pe), Rv = r or 0 and Cv = 0 or cf[ch - D].
 * Per chunk of D18_CH neighbours, their Gaussians first (D18_NN neighbours' exps in
 * lockstep), then the max / sum pass. */
#define D18_NV 7
#ifndef D18_CH
#define D18_CH 8
#endif
#ifndef D18_NN
#define D18_NN 2  /* <= 2: exp2_neg_zero_n holds 8 chains */
#endif
typedef struct {
    float sB[8], K0[8], K2[8], tr[8];  /* s c of B lanes; L, T factors; 2 mu, -2 mu */
    float Rv[D18_NV][8];               /* r on offset lanes, else 0 */
    int32_t gi[D18_NV][8];             /* cf index of centre lanes, else 0 */
    int32_t gm[D18_NV][8];             /* -1 on centre lanes */
    int32_t ch[D18_NV][8];             /* output channel, -1 for none */
    int st[D18_NV];                    /* row offset of lane 0 */
} d18_tab;

int pgn_d18_ok(int64_t D, float q) {
    const int64_t n = 2 * D / 3;
    /* s^2 = -q log2(e) <= 8 (sigma >= 0.3): K and R stay within a few dozen binades near
     * the derived Gaussians' peaks, so their rounding stays at ~1e-7 relative */
    return 8 < n && n <= 18 && n % 2 == 0 && -q * 1.44269504088896341f <= 8.0f;
}

static void d18_setup(d18_tab *tb, int64_t D, const float *cents, float s, float r) {
    const int64_t n = 2 * D / 3;
    const double h = 2.0 / (double)(n + 1);
    double sc[24], mu = 0.0;  /* s c_j as the direct path rounds it; virtual past n */
    for (int j = 0; j < 24; ++j)
        sc[j] = j < n ? (double)(cents[j] * s) : (double)(float)((-1.0 + (j + 1) * h) * s);
    for (int l = 0; l < 8; ++l) mu += (sc[8 + l] - sc[l]) / 8.0;
    memset(tb, 0, sizeof(*tb));
    for (int l = 0; l < 8; ++l) {
        tb->sB[l] = (float)sc[8 + l];
        tb->K0[l] = (float)exp2(sc[8 + l] * sc[8 + l] - sc[l] * sc[l]);
        tb->K2[l] = l < 6 ? (float)exp2(sc[8 + l % 2] * sc[8 + l % 2]
                                        - sc[16 + l % 2] * sc[16 + l % 2]) : 0.0f;
        tb->tr[l] = l < 3 ? (float)(2.0 * mu * s) : l >= 4 && l < 7 ? (float)(-2.0 * mu * s) : 0.0f;
    }
    for (int v = 0; v < D18_NV; ++v) {
        tb->st[v] = v < 3 ? (int)(v * n) : v < 6 ? (int)((v - 3) * n + 8) : 16;
        for (int l = 0; l < 8; ++l) {
            int64_t c = -1;
            if (v < 6 && (v < 3 || 8 + l < n)) c = tb->st[v] + l;
            if (v == 6 && n > 16 && l < 6) c = (l / 2) * n + 16 + l % 2;
            tb->ch[v][l] = (int32_t)c;
            if (c >= 0 && c < D) {
                tb->Rv[v][l] = r;
            } else if (c >= D) {
                tb->gi[v][l] = (int32_t)(c - D);
                tb->gm[v][l] = -1;
            }
        }
    }
}

/* 2^-t of NE vectors in lockstep (independent chains side by side in the instruction
 * stream: the core's out-of-order window sees all of them), exactly 0 where t > 125. */
static inline __attribute__((always_inline)) void exp2_neg_zero_n(__m256 *t, const int NE) {
    __m256 keep[8], k[8], f[8], p[8];
    for (int e = 0; e < NE; ++e) {
        keep[e] = _mm256_cmp_ps(t[e], _mm256_set1_ps(125.0f), _CMP_LE_OQ);
        k[e] = _mm256_round_ps(t[e], _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    }
    for (int e = 0; e < NE; ++e) f[e] = _mm256_sub_ps(k[e], t[e]);
    for (int e = 0; e < NE; ++e)
        p[e] = _mm256_fmadd_ps(_mm256_set1_ps(PGN_EXP2_C5), f[e], _mm256_set1_ps(PGN_EXP2_C4));
    for (int e = 0; e < NE; ++e) p[e] = _mm256_fmadd_ps(p[e], f[e], _mm256_set1_ps(PGN_EXP2_C3));
    for (int e = 0; e < NE; ++e) p[e] = _mm256_fmadd_ps(p[e], f[e], _mm256_set1_ps(PGN_EXP2_C2));
    for (int e = 0; e < NE; ++e) p[e] = _mm256_fmadd_ps(p[e], f[e], _mm256_set1_ps(PGN_EXP2_C1));
    for (int e = 0; e < NE; ++e) p[e] = _mm256_fmadd_ps(p[e], f[e], _mm256_set1_ps(PGN_EXP2_C0));
    for (int e = 0; e < NE; ++e) {
        const __m256i k23 = _mm256_slli_epi32(_mm256_cvtps_epi32(k[e]), 23);
        t[e] = _mm256_and_ps(
            _mm256_castsi256_ps(_mm256_sub_epi32(_mm256_castps_si256(p[e]), k23)), keep[e]);
    }
}

/* The NV pe vectors of NN neighbours (w: their offsets, 3 floats each, one more readable)
 * into pe + i * 8 * D18_NV. Broadcasts from memory, not lane permutes (slow on Zen). */
static inline __attribute__((always_inline)) void d18_pe(const float *w, float s,
                                                         const d18_tab *tb, float *pe,
                                                         const int NV, const int NN) {
    const __m256 sB = _mm256_load_ps(tb->sB), vs = _mm256_set1_ps(s);
    __m256 x[8];  /* per neighbour: B_0, B_1, B_2, R */
    for (int i = 0; i < NN; ++i) {
        for (int a = 0; a < 3; ++a) {
            const __m256 u = _mm256_fnmadd_ps(_mm256_broadcast_ss(w + 3 * i + a), vs, sB);
            x[4 * i + a] = _mm256_mul_ps(u, u);
        }
        /* R lanes 0..2: 2^(-2 mu s w_a) (for L), 4..6: 2^(2 mu s w_a) (for T) */
        const __m256 tr = _mm256_mul_ps(_mm256_broadcast_ps((const __m128 *)(w + 3 * i)),
                                        _mm256_load_ps(tb->tr));
        x[4 * i + 3] = _mm256_max_ps(tr, _mm256_set1_ps(-126.0f));
    }
    exp2_neg_zero_n(x, 4 * NN);
    const __m256 K0 = _mm256_load_ps(tb->K0);
    for (int i = 0; i < NN; ++i) {
        float *o = pe + i * 8 * D18_NV;
        const __m256 *b = x + 4 * i, R = x[4 * i + 3];
        /* R's halves side by side, then in-lane broadcasts (vpermps is slow on Zen) */
        const __m256 RL = _mm256_permute2f128_ps(R, R, 0x00), RT = _mm256_permute2f128_ps(R, R, 0x11);
        const __m256 RLa[3] = {_mm256_permute_ps(RL, 0x00), _mm256_permute_ps(RL, 0x55),
                               _mm256_permute_ps(RL, 0xaa)};
        for (int a = 0; a < 3; ++a) {
            _mm256_store_ps(o + 8 * (3 + a), b[a]);
            _mm256_store_ps(o + 8 * a, _mm256_mul_ps(_mm256_mul_ps(b[a], K0), RLa[a]));
        }
        if (NV == 7) {  /* else RT is unused: the compiler drops it */
            /* lanes 0, 1 of B_0, B_1, B_2 side by side */
            const __m256 lo = _mm256_castpd_ps(_mm256_unpacklo_pd(_mm256_castps_pd(b[0]),
                                                                  _mm256_castps_pd(b[1])));
            const __m256 bt = _mm256_insertf128_ps(lo, _mm256_castps256_ps128(b[2]), 1);
            const __m256 R3 = _mm256_permutevar_ps(RT, _mm256_setr_epi32(0, 0, 1, 1, 2, 2, 3, 3));
            _mm256_store_ps(o + 8 * 6, _mm256_mul_ps(_mm256_mul_ps(bt, _mm256_load_ps(tb->K2)), R3));
        }
    }
}

static inline __attribute__((always_inline)) void d18_body(
        const float *feat, int64_t D, const int64_t *cidx, const int32_t *nb, int64_t S,
        int64_t K, const float *vx, float s, const d18_tab *tb, float *out, float *acc,
        const int NV) {
    const int64_t Dp = 32, D2p = padded(2 * D);
    float pb[(D18_CH + D18_NN) * 8 * D18_NV] __attribute__((aligned(32)));  /* a chunk's pe */
    const float invk = 1.0f / (float)K;
    float *cv = acc + 64;  /* (NV, 8) per-centre Cv */
    const int pure_l1 = 2 * D / 3 >= 16;  /* L_1 (channels n..n+7) all below D */
    for (int64_t c = 0; c < S; ++c) {
        const float *cf = feat + cidx[c] * Dp;
        const int32_t *nr = nb + c * K;
        const float *vc = vx + c * K * 3;
        __m256 mx[D18_NV], sm[D18_NV];
        for (int v = 0; v < NV; ++v) {
            const __m256i gi = _mm256_load_si256((const __m256i *)tb->gi[v]);
            const __m256 gm = _mm256_castsi256_ps(_mm256_load_si256((const __m256i *)tb->gm[v]));
            _mm256_store_ps(cv + 8 * v, _mm256_mask_i32gather_ps(_mm256_setzero_ps(), cf, gi, gm, 4));
            mx[v] = _mm256_set1_ps(-INFINITY);
            sm[v] = _mm256_setzero_ps();
        }
        /* chunks of D18_CH neighbours: their Gaussians first (independent chains, long
         * ones), then the max / sum pass (short chains into the accumulators) */
        for (int64_t t0 = 0; t0 < K; t0 += D18_CH) {
            const int64_t nt = K - t0 < D18_CH ? K - t0 : D18_CH;
            for (int64_t i = 0; i < nt; i += D18_NN)
                d18_pe(vc + (t0 + i) * 3, s, tb, pb + i * 8 * D18_NV, NV, D18_NN);
            for (int64_t i = 0; i < nt; ++i) {
                const float *row = feat + (int64_t)nr[t0 + i] * Dp;
                const float *pi = pb + i * 8 * D18_NV;
                for (int v = 0; v < NV; ++v) {
                    const __m256 pe = _mm256_load_ps(pi + 8 * v);
                    __m256 x;
                    /* lanes with offsets: L_0, L_1, B_0 always; B_1 and T where n = 18;
                     * offset lanes only (Cv = 0): L_0, B_0, and L_1 where n >= 16 */
                    if (v == 0 || v == 1 || v == 3 || (NV == 7 && (v == 4 || v == 6))) {
                        const __m256 e = _mm256_sub_ps(_mm256_loadu_ps(row + tb->st[v]),
                                                       _mm256_loadu_ps(cf + tb->st[v]));
                        const __m256 c = v == 0 || v == 3 || (v == 1 && pure_l1)
                            ? pe : _mm256_add_ps(_mm256_load_ps(cv + 8 * v), pe);
                        x = _mm256_fmadd_ps(e, _mm256_load_ps(tb->Rv[v]), c);
                    } else {
                        x = _mm256_add_ps(_mm256_load_ps(cv + 8 * v), pe);
                    }
                    const __m256 w = _mm256_mul_ps(x, pe);
                    mx[v] = _mm256_max_ps(mx[v], w);
                    sm[v] = _mm256_add_ps(sm[v], w);
                }
            }
        }
        const __m256 ik = _mm256_set1_ps(invk);
        for (int v = 0; v < NV; ++v) _mm256_store_ps(acc + 8 * v, _mm256_fmadd_ps(sm[v], ik, mx[v]));
        float *o = out + c * D2p;
        for (int v = 0; v < NV; ++v)
            for (int l = 0; l < 8; ++l)
                if (tb->ch[v][l] >= 0) o[tb->ch[v][l]] = acc[8 * v + l];
        /* in channel order, so that gelu vectorises (libmvec erff: ~10x the scalar rate) */
#pragma omp simd
        for (int64_t d = 0; d < 2 * D; ++d) o[d] = gelu(o[d]);
        for (int64_t d = 2 * D; d < D2p; ++d) o[d] = 0.0f;
    }
}

/* All S centres of stage 1 where pgn_d18_ok(D, q); cents: the n centres of one axis;
 * s = sqrt(-q log2 e); acc: 128 floats, 32-byte aligned. */
void pgn_aggregate_d18_avx2(const float *feat, int64_t D, const int64_t *cidx,
                            const int32_t *nb, int64_t S, int64_t K, const float *vx,
                            float r, const float *cents, float s, float *out, float *acc) {
    d18_tab tb __attribute__((aligned(32)));
    d18_setup(&tb, D, cents, s, r);
    if (2 * D / 3 > 16)
        d18_body(feat, D, cidx, nb, S, K, vx, s, &tb, out, acc, 7);
    else
        d18_body(feat, D, cidx, nb, S, K, vx, s, &tb, out, acc, 6);
}

/* Separable stages with AVX2 (blocks of 8), as pgn_aggregate_sep_avx512's sep_pass: pe is
 * never stored; the pe of a block is A[t, a, m] * (T[m, 0..8) * P[t, a]^(0..8)), the powers
 * by blends of P, P^2, P^4 multiplied in the same order as the AVX-512 masked multiplies.
 * AVX2 has no cheap masked store, so max and sum live in a per-axis padded layout (axis a
 * at a * 8M, lanes past its n centres computed and ignored) and a block never spills into
 * the next axis. G: per lane cf[ch] (ch < D) or cf[ch - D]; RV: r where ch < D, else 0;
 * G2: 0 where ch < D, else G. */
#ifndef SEP_NT
#define SEP_NT 8  /* neighbours per pass: one max / sum update per block */
#endif
static inline __attribute__((always_inline)) void sep_pass8(
        const float *const *rows, int nt, int64_t t0, int64_t nta, const sep_t *fx,
        const float *G, const float *RV, const float *G2, float *mx, float *sm) {
    const int64_t n = fx->n, M = fx->M;
    const __m256 one = _mm256_set1_ps(1.0f);
    const __m256 b1 = _mm256_castsi256_ps(_mm256_setr_epi32(0, -1, 0, -1, 0, -1, 0, -1));
    const __m256 b2 = _mm256_castsi256_ps(_mm256_setr_epi32(0, 0, -1, -1, 0, 0, -1, -1));
    const __m256 b4 = _mm256_castsi256_ps(_mm256_setr_epi32(0, 0, 0, 0, -1, -1, -1, -1));
    for (int a = 0; a < 3; ++a) {
        __m256 e[SEP_NT];
        for (int i = 0; i < nt; ++i) {
            const int64_t ta = 3 * (t0 + i) + a;
            const __m256 p1 = _mm256_blendv_ps(one, _mm256_set1_ps(fx->E[1 * nta + ta]), b1);
            const __m256 p2 = _mm256_blendv_ps(one, _mm256_set1_ps(fx->E[2 * nta + ta]), b2);
            const __m256 p4 = _mm256_blendv_ps(one, _mm256_set1_ps(fx->E[4 * nta + ta]), b4);
            e[i] = _mm256_mul_ps(_mm256_mul_ps(p1, p2), p4);
        }
        for (int64_t m = 0; m < M; ++m) {
            const int64_t ch = a * n + 8 * m, pa = (a * M + m) * 8;
            const __m256 T = _mm256_loadu_ps(fx->T + 8 * m);
            const __m256 g = _mm256_load_ps(G + pa);
            const __m256 rv = _mm256_load_ps(RV + pa), g2 = _mm256_load_ps(G2 + pa);
            const int any_off = !_mm256_testz_si256(_mm256_castps_si256(rv),
                                                    _mm256_castps_si256(rv));
            __m256 w[SEP_NT];
            for (int i = 0; i < nt; ++i) {
                const __m256 am = _mm256_set1_ps(fx->A[m * nta + 3 * (t0 + i) + a]);
                const __m256 pe = _mm256_mul_ps(am, _mm256_mul_ps(T, e[i]));
                if (any_off) {
                    /* lanes past D read on into the next row or the table's slack
                     * (pgn_encode.c allocates 16 floats more), finite: times 0 below.
                     * ((row - g) r + pe) pe where ch < D, else (g + pe) pe, as one fma
                     * (axis 0: n <= D channels, all offsets, G2 = 0) */
                    const __m256 row = _mm256_loadu_ps(rows[i] + ch);
                    const __m256 x = _mm256_fmadd_ps(_mm256_sub_ps(row, g), rv,
                                                     a == 0 ? pe : _mm256_add_ps(g2, pe));
                    w[i] = _mm256_mul_ps(x, pe);
                } else {
                    w[i] = _mm256_mul_ps(_mm256_add_ps(g, pe), pe);
                }
            }
            __m256 wm = w[0], ws = w[0];
            if (nt == SEP_NT) {  /* pairwise trees */
                __m256 tm[SEP_NT], ts[SEP_NT];
                for (int i = 0; i < SEP_NT; ++i) tm[i] = ts[i] = w[i];
                for (int h = SEP_NT / 2; h >= 1; h /= 2)
                    for (int i = 0; i < h; ++i) {
                        tm[i] = _mm256_max_ps(tm[2 * i], tm[2 * i + 1]);
                        ts[i] = _mm256_add_ps(ts[2 * i], ts[2 * i + 1]);
                    }
                wm = tm[0];
                ws = ts[0];
            }
            _mm256_store_ps(mx + pa, _mm256_max_ps(wm, _mm256_load_ps(mx + pa)));
            _mm256_store_ps(sm + pa, _mm256_add_ps(_mm256_load_ps(sm + pa), ws));
        }
    }
}

/* All S centres of a separable stage (fx->B == 8). mx, sm, G, RV, G2, SRC: 3 * 8 * fx->M
 * floats (SRC: int32) each, 32-byte aligned. */
void pgn_aggregate_sep_avx2(const float *feat, int64_t D, const int64_t *cidx,
                            const int32_t *nb, int64_t S, int64_t K, const float *vx,
                            float r, float *out, float *mx, float *sm, float *G, float *RV,
                            float *G2, int32_t *SRC, sep_t *fx) {
    const int64_t Dp = padded(D), D2 = 2 * D, D2p = padded(D2), nta = 3 * K;
    const int64_t n = fx->n, M = fx->M, np = 3 * 8 * M;
    const float invk = 1.0f / (float)K;
    for (int64_t p = 0; p < np; ++p) {
        const int64_t a = p / (8 * M), j = p % (8 * M), ch = a * n + j;
        RV[p] = j < n && ch < D ? r : 0.0f;
        SRC[p] = j < n ? (int32_t)(ch < D ? ch : ch - D) : -1;  /* G's source channel */
    }
    for (int64_t c = 0; c < S; ++c) {
        const float *cf = feat + cidx[c] * Dp;
        const int32_t *nr = nb + c * K;
        for (int64_t p = 0; p < np; ++p) {
            G[p] = SRC[p] >= 0 ? cf[SRC[p]] : 0.0f;
            G2[p] = RV[p] != 0.0f ? 0.0f : G[p];
            mx[p] = -INFINITY;
            sm[p] = 0.0f;
        }
        pgn_sep_prepare(fx, vx + c * K * 3, K);
        int64_t t = 0;
        for (; t + SEP_NT <= K; t += SEP_NT) {
            const float *rows[SEP_NT];
            for (int i = 0; i < SEP_NT; ++i) rows[i] = feat + (int64_t)nr[t + i] * Dp;
            sep_pass8(rows, SEP_NT, t, nta, fx, G, RV, G2, mx, sm);
        }
        for (; t < K; ++t) {
            const float *rows[1] = {feat + (int64_t)nr[t] * Dp};
            sep_pass8(rows, 1, t, nta, fx, G, RV, G2, mx, sm);
        }
        float *o = out + c * D2p;
        for (int a = 0; a < 3; ++a)
            for (int64_t j = 0; j < n; ++j) {
                const int64_t p = a * 8 * M + j;
                o[a * n + j] = gelu(mx[p] + sm[p] * invk);
            }
        for (int64_t d = D2; d < D2p; ++d) o[d] = 0.0f;
    }
}

/* Sums of e = row[d] - cf[d] and e^2 over one centre's K neighbour rows, channels
 * [0, Dp), as pgn_std_centre_avx512: chunks of up to 4 vectors whose 8 partial sums stay
 * in registers over all K rows (8 independent add chains hide the add latency). */
#define PGN_STDCHUNK(NV)                                                                 \
    static inline void stdchunk##NV(const float *feat, int64_t Dp, const int32_t *nr,    \
                                    int64_t K, const float *cf, __m256 *t1, __m256 *t2) { \
        __m256 a1[NV], a2[NV], g[NV];                                                    \
        for (int v = 0; v < NV; ++v) {                                                   \
            g[v] = _mm256_load_ps(cf + 8 * v);                                           \
            a1[v] = a2[v] = _mm256_setzero_ps();                                         \
        }                                                                                \
        for (int64_t t = 0; t < K; ++t) {                                                \
            const float *r0 = feat + (int64_t)nr[t] * Dp;                                \
            for (int v = 0; v < NV; ++v) {                                               \
                const __m256 e0 = _mm256_sub_ps(_mm256_load_ps(r0 + 8 * v), g[v]);       \
                a1[v] = _mm256_add_ps(a1[v], e0);                                        \
                a2[v] = _mm256_fmadd_ps(e0, e0, a2[v]);                                  \
            }                                                                            \
        }                                                                                \
        for (int v = 0; v < NV; ++v) {                                                   \
            *t1 = _mm256_add_ps(*t1, a1[v]);                                             \
            *t2 = _mm256_add_ps(*t2, a2[v]);                                             \
        }                                                                                \
    }
PGN_STDCHUNK(1)
PGN_STDCHUNK(2)
PGN_STDCHUNK(3)
PGN_STDCHUNK(4)
#undef PGN_STDCHUNK

static inline float hsum8(__m256 v) {
    __m128 s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
    s = _mm_add_ps(s, _mm_movehl_ps(s, s));
    s = _mm_add_ss(s, _mm_movehdup_ps(s));
    return _mm_cvtss_f32(s);
}

void pgn_std_centre_avx2(const float *feat, int64_t Dp, const int32_t *nr, int64_t K,
                         const float *cf, float *a1, float *a2) {
    __m256 t1 = _mm256_setzero_ps(), t2 = t1;
    int64_t v = 0;
    const int64_t nv = Dp / 8;
    for (; v + 4 <= nv; v += 4) stdchunk4(feat + 8 * v, Dp, nr, K, cf + 8 * v, &t1, &t2);
    switch (nv - v) {
        case 3: stdchunk3(feat + 8 * v, Dp, nr, K, cf + 8 * v, &t1, &t2); break;
        case 2: stdchunk2(feat + 8 * v, Dp, nr, K, cf + 8 * v, &t1, &t2); break;
        case 1: stdchunk1(feat + 8 * v, Dp, nr, K, cf + 8 * v, &t1, &t2); break;
        default: break;
    }
    *a1 = hsum8(t1);
    *a2 = hsum8(t2);
}
#endif

/* ISO C wants a non-empty translation unit when AVX2 is off */
typedef int pgn_avx2_unit;
