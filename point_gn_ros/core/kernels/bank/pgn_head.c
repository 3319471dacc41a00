/* The compiled head: one query through a bank section's head (its Python caller in bank/).
 *
 * The torch reference runs ~40 small ops per query, each of which starts with its code and
 * data out of cache after a sensor's idle gap. Here the same formulas run in two calls
 * around the search (bank_dots or the index's candidates):
 *
 * pgn_head_embed: x (D) raw features -> xs (D) = normalize((x - mean) / scale),
 *   z (d) = normalize(((x - mean) / scale) @ P)  (P (D, d) row-major; NULL: z = xs),
 *   u (d) = normalize(z @ W)                    (W (d, d);           NULL: u = z).
 * pgn_head_finish: the cosines of the entries that vote -> calibrated probabilities (C):
 *   log vote shares (each entry at least exp(-80) of the best one's vote, every entry not
 *   among sims counted at that floor, -inf for classes without entries), + ridge_weight x
 *   kernel ridge scores, + the vote bias, + fusion_weight x LDA log-posteriors, softmax / T.
 * pgn_head_linear: out (C) = coef (C, dim) @ in + bias (the gate's two logits).
 *
 * Sums run in double; the results agree with the torch path to ~1e-7 (test_lone_head.py).
 * No fast-math: -inf marks absent classes and must propagate.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#define LOGIT_FLOOR (-80.0)
/* entries a pass of pgn_head_finish: their exponentials in vectors, then their sums */
#define FINISH_CHUNK 256

/* exp(x) in double for x in [-708, 709] (callers' arguments are <= 0 and >= -160):
 * Cody-Waite reduction by ln 2 (the high part has 11 trailing zero bits, so n ln2_hi is
 * exact) and the Taylor polynomial of degree 13 on |r| <= ln 2 / 2 (truncation < 5e-18),
 * within 2 ulp of libm's exp. Branch-free and call-free, so the loops below vectorise. */
static inline double exp_d(double x) {
    const double n = __builtin_rint(x * 1.4426950408889634);
    double r = x - n * 0.693145751953125;
    r = r - n * 1.4286068203094172e-06;
    double p = 1.0 / 6227020800.0;
    p = p * r + 1.0 / 479001600.0;
    p = p * r + 1.0 / 39916800.0;
    p = p * r + 1.0 / 3628800.0;
    p = p * r + 1.0 / 362880.0;
    p = p * r + 1.0 / 40320.0;
    p = p * r + 1.0 / 5040.0;
    p = p * r + 1.0 / 720.0;
    p = p * r + 1.0 / 120.0;
    p = p * r + 1.0 / 24.0;
    p = p * r + 1.0 / 6.0;
    p = p * r + 0.5;
    p = p * r + 1.0;
    p = p * r + 1.0;
    const int64_t bits = ((int64_t)n + 1023) << 52;
    double scale;
    memcpy(&scale, &bits, 8);
    return p * scale;
}

typedef double hv4 __attribute__((vector_size(32)));
typedef float hf4 __attribute__((vector_size(16)));

/* sum[c] += sum over the n entries j of k[j] a[j C + c], for C = 4 NB classes: the 4 NB
 * column sums in registers (a runtime C kept them in memory, each entry waiting on the
 * last one's store), each in entry order. */
#define PGN_RIDGE_ACC(NB)                                                                 \
    static void ridge_acc##NB(const double *k, const float *a, int64_t n, double *sum) {  \
        hv4 acc[NB];                                                                      \
        for (int b = 0; b < NB; ++b) acc[b] = (hv4){0.0, 0.0, 0.0, 0.0};                  \
        for (int64_t j = 0; j < n; ++j) {                                                 \
            const hv4 kj = {k[j], k[j], k[j], k[j]};                                      \
            for (int b = 0; b < NB; ++b) {                                                \
                hf4 f;                                                                    \
                memcpy(&f, a + j * 4 * NB + 4 * b, sizeof(f));                            \
                acc[b] += kj * __builtin_convertvector(f, hv4);                           \
            }                                                                             \
        }                                                                                 \
        for (int b = 0; b < NB; ++b)                                                      \
            for (int l = 0; l < 4; ++l) sum[4 * b + l] += acc[b][l];                      \
    }
PGN_RIDGE_ACC(1) PGN_RIDGE_ACC(2) PGN_RIDGE_ACC(3) PGN_RIDGE_ACC(4) PGN_RIDGE_ACC(5)
PGN_RIDGE_ACC(6) PGN_RIDGE_ACC(7) PGN_RIDGE_ACC(8) PGN_RIDGE_ACC(9) PGN_RIDGE_ACC(10)
PGN_RIDGE_ACC(11) PGN_RIDGE_ACC(12) PGN_RIDGE_ACC(13) PGN_RIDGE_ACC(14) PGN_RIDGE_ACC(15)
PGN_RIDGE_ACC(16)
#undef PGN_RIDGE_ACC

/* sum (C) += k (n) @ a (n, C): in registers for C = 4, 8, ..., 64, else entry by entry */
static void ridge_acc(const double *k, const float *a, int64_t n, int64_t C, double *sum) {
    static void (*const acc[17])(const double *, const float *, int64_t, double *) = {
        NULL, ridge_acc1, ridge_acc2, ridge_acc3, ridge_acc4, ridge_acc5, ridge_acc6,
        ridge_acc7, ridge_acc8, ridge_acc9, ridge_acc10, ridge_acc11, ridge_acc12,
        ridge_acc13, ridge_acc14, ridge_acc15, ridge_acc16};
    if (C % 4 == 0 && C / 4 <= 16) {
        acc[C / 4](k, a, n, sum);
        return;
    }
    for (int64_t j = 0; j < n; ++j)
        for (int64_t c = 0; c < C; ++c) sum[c] += k[j] * a[j * C + c];
}

/* v (n) /= max(||v||, 1e-12), as torch.nn.functional.normalize */
static void normalize(float *v, int64_t n) {
    double s = 0.0;
    for (int64_t i = 0; i < n; ++i) s += (double)v[i] * v[i];
    const float norm = (float)sqrt(s);
    const float den = norm > 1e-12f ? norm : 1e-12f;
    for (int64_t i = 0; i < n; ++i) v[i] /= den;
}

/* out (d) = v (D) @ M (D, d), float32 rows accumulated in float32 lanes (M streamed once) */
static void row_times(const float *v, int64_t D, const float *M, int64_t d, float *out) {
    memset(out, 0, (size_t)d * sizeof(float));
    for (int64_t i = 0; i < D; ++i) {
        const float a = v[i];
        const float *m = M + i * d;
        for (int64_t j = 0; j < d; ++j) out[j] += a * m[j];
    }
}

void pgn_head_embed(const float *x, int64_t D, const float *mean, const float *scale,
                    const float *P, int64_t d, const float *W, float *xs, float *z,
                    float *u) {
    for (int64_t i = 0; i < D; ++i) xs[i] = (x[i] - mean[i]) / scale[i];
    if (P != NULL) row_times(xs, D, P, d, z);
    normalize(xs, D);
    if (P == NULL) memcpy(z, xs, (size_t)D * sizeof(float));
    else normalize(z, d);
    if (W != NULL) {
        row_times(z, d, W, d, u);
        normalize(u, d);
    } else {
        memcpy(u, z, (size_t)d * sizeof(float));
    }
}

void pgn_head_linear(const float *in, int64_t dim, const float *coef, int64_t C,
                     const float *bias, double *out) {
    /* four double lanes times two chains: a single running sum waited on its adds' latency
     * (~20 us for the shipped bank's 40 x 512 LDA) */
    for (int64_t c = 0; c < C; ++c) {
        const float *w = coef + c * dim;
        hv4 s0 = {0.0, 0.0, 0.0, 0.0}, s1 = s0;
        int64_t j = 0;
        for (; j + 8 <= dim; j += 8) {
            hf4 a0, a1, b0, b1;
            memcpy(&a0, w + j, sizeof(a0)); memcpy(&a1, w + j + 4, sizeof(a1));
            memcpy(&b0, in + j, sizeof(b0)); memcpy(&b1, in + j + 4, sizeof(b1));
            s0 += __builtin_convertvector(a0, hv4) * __builtin_convertvector(b0, hv4);
            s1 += __builtin_convertvector(a1, hv4) * __builtin_convertvector(b1, hv4);
        }
        const hv4 t = s0 + s1;
        double s = (t[0] + t[1]) + (t[2] + t[3]);
        for (; j < dim; ++j) s += (double)w[j] * in[j];
        out[c] = s + bias[c];
    }
}

/* v (C) -= logsumexp over its finite entries (all -inf: left as is) */
static void log_normalize(double *v, int64_t C) {
    double top = -INFINITY;
    for (int64_t c = 0; c < C; ++c) if (v[c] > top) top = v[c];
    if (!isfinite(top)) return;
    double s = 0.0;
    for (int64_t c = 0; c < C; ++c) s += exp(v[c] - top);
    const double lse = top + log(s);
    for (int64_t c = 0; c < C; ++c) v[c] -= lse;
}

/* sims (M) with labels (M) in [0, C); counts (C) entries per class in the section;
 * ridge_coef (M, C) float32 or NULL (then M is the whole section, in its row order);
 * lda_coef (C, lda_dim) or NULL; work: 5 C doubles.
 * -> prob (C) float32, *novelty = max(1 - best cosine, 0). Returns 0, or -1 for M < 1. */
int pgn_head_finish(const float *sims, const int64_t *labels, int64_t M, int64_t C,
                    const int64_t *counts, double gamma,
                    const float *ridge_coef, double ridge_gamma, double ridge_weight,
                    const float *lda_in, int64_t lda_dim, const float *lda_coef,
                    const float *lda_bias, double fusion_weight, double temperature,
                    double *work, float *prob, float *novelty) {
    if (M < 1) return -1;
    double *votes = work, *fused = work + C, *aux = work + 2 * C;
    float best = sims[0];
#pragma omp simd reduction(max:best)
    for (int64_t i = 1; i < M; ++i) best = sims[i] > best ? sims[i] : best;
    /* the torch path's float32 logits: (s - 1) * gamma, relative to the best entry's */
    const float g = (float)gamma, top = (best - 1.0f) * g;
    /* votes of even and odd entries apart (two chains of dependent adds, not one) */
    double *votes2 = work + 4 * C;
    memset(votes, 0, (size_t)C * sizeof(double));
    memset(votes2, 0, (size_t)C * sizeof(double));
    int64_t *seen = (int64_t *)aux;              /* aux reused below, after the votes */
    /* every entry of the section among sims (an exact scan): seen = counts, not counted */
    int64_t total = 0;
    for (int64_t c = 0; c < C; ++c) total += counts[c];
    const int all = M == total;
    memset(seen, 0, (size_t)C * sizeof(int64_t));
    const int ridge = ridge_coef != NULL && ridge_weight != 0.0;
    double *ridge_sum = ridge ? work + 3 * C : NULL;
    if (ridge) memset(ridge_sum, 0, (size_t)C * sizeof(double));
    float ev[FINISH_CHUNK];
    double kr[FINISH_CHUNK];
    for (int64_t i0 = 0; i0 < M; i0 += FINISH_CHUNK) {
        const int64_t n = M - i0 < FINISH_CHUNK ? M - i0 : FINISH_CHUNK;
        const float *s = sims + i0;
        /* each vote as expf would give it: float logits, the exponential rounded to float;
         * the floor as max(l, F) = ((l + F) + |l - F|) / 2, exact in double for a float l
         * and F = -80, and branch-free (a compare and select would stop the vectoriser) */
#pragma omp simd
        for (int64_t j = 0; j < n; ++j) {
            const double l = (double)((s[j] - 1.0f) * g - top);
            ev[j] = (float)exp_d(0.5 * ((l + LOGIT_FLOOR) + fabs(l - LOGIT_FLOOR)));
        }
        const int64_t *lb = labels + i0;
        int64_t j = 0;
        for (; j + 2 <= n; j += 2) {
            votes[lb[j]] += (double)ev[j];
            votes2[lb[j + 1]] += (double)ev[j + 1];
        }
        if (j < n) votes[lb[j]] += (double)ev[j];
        if (!all)
            for (j = 0; j < n; ++j) seen[lb[j]] += 1;
        if (!ridge) continue;
#pragma omp simd
        for (int64_t j = 0; j < n; ++j) kr[j] = exp_d(ridge_gamma * ((double)s[j] - 1.0));
        ridge_acc(kr, ridge_coef + i0 * C, n, C, ridge_sum);
    }
    const double floor_vote = exp(LOGIT_FLOOR);
    for (int64_t c = 0; c < C; ++c) {
        votes[c] += votes2[c];
        if (all) seen[c] = counts[c];
        const double v = votes[c] + (double)(counts[c] - seen[c]) * floor_vote;
        fused[c] = counts[c] > 0 ? log(v > 1.1754943508222875e-38 ? v : 1.1754943508222875e-38)
                                 : -INFINITY;
    }
    log_normalize(fused, C);
    if (ridge)
        for (int64_t c = 0; c < C; ++c) fused[c] += ridge_weight * (double)(float)ridge_sum[c];
    if (lda_coef != NULL && fusion_weight != 0.0) {
        pgn_head_linear(lda_in, lda_dim, lda_coef, C, lda_bias, aux);
        log_normalize(aux, C);
        for (int64_t c = 0; c < C; ++c) fused[c] += fusion_weight * aux[c];
    }
    for (int64_t c = 0; c < C; ++c) fused[c] /= temperature;
    log_normalize(fused, C);
    for (int64_t c = 0; c < C; ++c) prob[c] = (float)exp(fused[c]);
    const float nov = 1.0f - best;
    *novelty = nov > 0.0f ? nov : 0.0f;
    return 0;
}
