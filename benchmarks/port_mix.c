/* Cycles a block step of the AVX-512 separable stages costs, by the mix of its operations
 * (benchmarks/log/2026-12-05.md, "fifth session"). Not part of the package: a measurement.
 *
 *     gcc -O3 -march=native -o port_mix benchmarks/port_mix.c && ./port_mix [GHz]
 *
 * Each variant runs NB = 4 blocks over K = 120 neighbours with its data in L1, like
 * sep_group16 (pgn_avx512_sep.c); cycles are thread CPU time times the clock given (default
 * 3.67, what `point_gn bench --profile`'s peak row implies on the 2-vCPU AMD EPYC).
 */
#include <immintrin.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#define K 120
#define NB 4
static float E16[K * 16] __attribute__((aligned(64)));
static float A[NB][K * 3];
static float rows[8 * 64 * NB + 64] __attribute__((aligned(64)));
static int nr[K];
static volatile unsigned short kmask = 0xffff;  /* a mask the compiler cannot fold */

static double now(void) {
    struct timespec ts;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

enum { OFF, OFF_MASKED_LOAD, CTR_INT_MAX_MIN, CTR_FLOAT_MAX_MIN, CTR_FLOAT_MAX, NVAR };
static const char *names[NVAR] = {
    "offset block, whole row load",
    "offset block, row load under a mask",
    "centre block, integer max and min",
    "centre block, float max and min",
    "centre block, float max only",
};

static inline __attribute__((always_inline)) void run_(const int v, float *out, long reps) {
    __m512 a1[NB], a2[NB], a3[NB], a4[NB], g[NB], rt[NB];
    __m512i i1[NB], i2[NB];
    const __mmask16 km = (__mmask16)kmask;
    for (int b = 0; b < NB; ++b) {
        a1[b] = a2[b] = a3[b] = a4[b] = _mm512_setzero_ps();
        i1[b] = i2[b] = _mm512_setzero_si512();
        g[b] = _mm512_set1_ps(0.1f * b);
        rt[b] = _mm512_set1_ps(1.1f);
    }
    for (long r = 0; r < reps; ++r)
        for (int t = 0; t < K; ++t) {
            __m512 e = _mm512_load_ps(E16 + t * 16);
            __asm__("" : "+v"(e));
            const float *row = rows + (nr[t] & 7) * 64 * NB;
            for (int b = 0; b < NB; ++b) {
                const __m512 pe = _mm512_mul_ps(_mm512_set1_ps(A[b][3 * t]), e);
                if (v == OFF || v == OFF_MASKED_LOAD) {
                    const __m512 rw = v == OFF ? _mm512_load_ps(row + 16 * b)
                                               : _mm512_maskz_loadu_ps(km, row + 16 * b);
                    const __m512 f = _mm512_fmadd_ps(_mm512_sub_ps(rw, g[b]), rt[b], pe);
                    const __m512 w = _mm512_mul_ps(f, pe);
                    a1[b] = _mm512_max_ps(a1[b], w);
                    a2[b] = _mm512_add_ps(a2[b], w);
                    continue;
                }
                if (v == CTR_INT_MAX_MIN) {
                    const __m512i pb = _mm512_castps_si512(pe);
                    i1[b] = _mm512_max_epu32(i1[b], pb);
                    i2[b] = _mm512_min_epu32(i2[b], pb);
                } else {
                    a3[b] = _mm512_max_ps(a3[b], pe);
                    if (v == CTR_FLOAT_MAX_MIN) a4[b] = _mm512_min_ps(a4[b], pe);
                }
                a1[b] = _mm512_add_ps(a1[b], pe);
                a2[b] = _mm512_fmadd_ps(pe, pe, a2[b]);
            }
        }
    __m512 s = _mm512_setzero_ps();
    for (int b = 0; b < NB; ++b)
        s = _mm512_add_ps(s, _mm512_add_ps(_mm512_add_ps(a1[b], a2[b]), _mm512_add_ps(
            _mm512_add_ps(a3[b], a4[b]), _mm512_castsi512_ps(_mm512_add_epi32(i1[b], i2[b])))));
    _mm512_storeu_ps(out, s);
}

/* one function a variant, so that each keeps its accumulators in registers */
#define VARIANT(V) \
    static __attribute__((noinline)) void run##V(float *o, long r) { run_(V, o, r); }
VARIANT(0) VARIANT(1) VARIANT(2) VARIANT(3) VARIANT(4)
static void (*const runs[NVAR])(float *, long) = {run0, run1, run2, run3, run4};

int main(int argc, char **argv) {
    const double ghz = argc > 1 ? atof(argv[1]) : 3.67;
    for (int i = 0; i < K * 16; ++i) E16[i] = 1.0f + 1e-3f * (float)i;
    for (int b = 0; b < NB; ++b)
        for (int i = 0; i < K * 3; ++i) A[b][i] = 0.5f;
    for (int i = 0; i < 8 * 64 * NB + 64; ++i) rows[i] = 0.01f * (float)i;
    for (int i = 0; i < K; ++i) nr[i] = i * 37;
    float out[16];
    const long reps = 20000;
    for (int v = 0; v < NVAR; ++v) {
        double best = 1e9;
        for (int k = 0; k < 5; ++k) {
            const double t0 = now();
            runs[v](out, reps);
            const double dt = now() - t0;
            best = dt < best ? dt : best;
        }
        printf("%-40s %.2f cycles a block step\n", names[v],
               best / ((double)reps * K * NB) * ghz * 1e9);
    }
    return out[0] == 12345.0f;
}
