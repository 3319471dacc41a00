/* Row-wise projection for bank/index.py's int8 index: out = x @ rot.
 *
 * Each output element is sum_k x[i, k] * rot[k, j] added in k order with separate multiply
 * and add (compiled without fast-math and with -ffp-contract=off: no reassociation, no FMA
 * contraction), so a row's result is the same bit for bit whichever rows it is computed
 * with. That lets an index append a bank's new rows and get exactly the codes a fresh build
 * over all rows gets (a BLAS GEMM's rounding depends on the batch shape).
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

enum { PJ_R = 6, PJ_C = 16 };   /* register tile: 6 rows x 16 columns */
typedef float pj_v8 __attribute__((vector_size(32)));

static inline pj_v8 pj_load(const float *p) { pj_v8 v; memcpy(&v, p, sizeof(v)); return v; }

/* out[i, j0 .. j0 + 16) for 6 rows x (row stride d); w: rot's columns j0.. packed (d, 16). */
static void tile(const float *x, int64_t nr, int64_t d, const float *w, float *out, int64_t r) {
    pj_v8 acc[PJ_R][2];
    memset(acc, 0, sizeof(acc));
    for (int64_t k = 0; k < d; ++k) {
        const pj_v8 w0 = pj_load(w + k * PJ_C), w1 = pj_load(w + k * PJ_C + 8);
        for (int i = 0; i < PJ_R; ++i) {
            const float a = x[i * d + k];
            acc[i][0] += a * w0;
            acc[i][1] += a * w1;
        }
    }
    for (int64_t i = 0; i < nr; ++i) memcpy(out + i * r, acc[i], sizeof(acc[i]));
}

/* x (n, d) row-major, rot (d, r) row-major -> out (n, r) row-major. */
void pgn_project_f32(const float *x, int64_t n, int64_t d, const float *rot, int64_t r,
                     float *out) {
    if (r % PJ_C == 0) {
        float *packed = malloc((size_t)(d * r) * sizeof(float));   /* (r / 16, d, 16) */
        if (packed != NULL) {
            for (int64_t c = 0; c < r / PJ_C; ++c)
                for (int64_t k = 0; k < d; ++k)
                    memcpy(packed + (c * d + k) * PJ_C, rot + k * r + c * PJ_C,
                           PJ_C * sizeof(float));
            float *pad = calloc((size_t)(PJ_R * d), sizeof(float));   /* the last rows */
            for (int64_t i = 0; pad != NULL && i < n; i += PJ_R) {
                const int64_t nr = n - i < PJ_R ? n - i : PJ_R;
                const float *xi = x + i * d;
                if (nr < PJ_R) {
                    memcpy(pad, xi, (size_t)(nr * d) * sizeof(float));
                    xi = pad;
                }
                for (int64_t c = 0; c < r / PJ_C; ++c)
                    tile(xi, nr, d, packed + c * d * PJ_C, out + i * r + c * PJ_C, r);
            }
            free(packed);
            if (pad != NULL) {
                free(pad);
                return;
            }
        }
    }
    for (int64_t i = 0; i < n; ++i) {
        float *o = out + i * r;
        memset(o, 0, (size_t)r * sizeof(float));
        for (int64_t k = 0; k < d; ++k) {
            const float a = x[i * d + k];
            for (int64_t j = 0; j < r; ++j) o[j] += a * rot[k * r + j];
        }
    }
}
