/* Stage 1 of the encoder on AVX2 + FMA (CPUs without AVX-512) with half the exps of
 * pgn_aggregate_narrow_avx2 (pgn_avx2.c): Gaussians of one block of centres per axis by
 * 2^-t, the others derived from them. Compiled only where PGN_AVX2 (pgn_common.h);
 * pgn_encode.c calls it where pgn_narrow_derived_ok(). */
#include "pgn_common.h"

#if defined(PGN_AVX2)
/* Stage 1 with half the exps (8 < n <= 18 centres per axis, n even: D = 18..27), the
 * arithmetic per pe element of pgn_aggregate_narrow_avx2 in axis-aligned vectors: per
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

int pgn_narrow_derived_ok(int64_t D, float q) {
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
    float cv[D18_NV * 8] __attribute__((aligned(32)));  /* (NV, 8) per-centre Cv */
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
        for (int64_t d = 2 * D; d < D2p; ++d) o[d] = 0.0f;
    }
}

/* All S centres of stage 1 where pgn_narrow_derived_ok(D, q); cents: the n centres of one axis;
 * s = sqrt(-q log2 e); acc: 56 floats, 32-byte aligned (the d32 kernels' 64 suffice). */
void pgn_aggregate_narrow_derived_avx2(const float *feat, int64_t D, const int64_t *cidx,
                            const int32_t *nb, int64_t S, int64_t K, const float *vx,
                            float r, const float *cents, float s, float *out, float *acc) {
    d18_tab tb __attribute__((aligned(32)));
    d18_setup(&tb, D, cents, s, r);
    if (2 * D / 3 > 16)
        d18_body(feat, D, cidx, nb, S, K, vx, s, &tb, out, acc, 7);
    else
        d18_body(feat, D, cidx, nb, S, K, vx, s, &tb, out, acc, 6);
}
#endif

/* ISO C wants a non-empty translation unit when AVX2 is off */
typedef int pgn_avx2_d18_unit;
