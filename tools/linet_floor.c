/* The same gathers as the liNet layer's feature-major Warp kernels, hand-written with AVX2 intrinsics
 * and OpenMP: forward, grad_x (over the transposed connectivity) and grad_weight with grad_bias, on
 * preallocated outputs. It measures how fast this machine can run the layer's work at all, a floor
 * no kernel of the same algorithm beats. Built and run by tools/linet_floor.py, which writes the
 * connectivity files it reads:  python tools/linet_floor.py
 *
 * usage: linet_floor DIR N R N_IN THREADS REPEATS   (DIR holds index.bin, t_offsets.bin,
 *        t_entries.bin, t_units.bin as int32). Each repeat first writes a 64 MiB buffer (untimed) so
 *        the caches start cold, as they do for an op between other work, then times the three
 *        kernels back to back; prints the median of the whole and the medians of the parts in ms.
 */
#include <immintrin.h>
#include <omp.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

enum { B = 64 }; /* batch rows: one 64-lane vector per feature, as in the Warp kernels */

static int N, R, N_IN;
static const int *index_, *t_offsets, *t_entries, *t_units;
static float *x, *y, *w, *gy, *gx, *gw, *gb;

static double now(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec + 1e-9 * t.tv_nsec;
}

static void *read_file(const char *dir, const char *name, size_t bytes) {
    char path[4096];
    snprintf(path, sizeof path, "%s/%s", dir, name);
    FILE *f = fopen(path, "rb");
    void *p = malloc(bytes);
    if (!f || !p || fread(p, 1, bytes, f) != bytes) {
        fprintf(stderr, "cannot read %zu bytes from %s\n", bytes, path);
        exit(1);
    }
    fclose(f);
    return p;
}

static float lane_sum(__m256 v) {
    __m128 s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
    s = _mm_hadd_ps(s, s);
    return _mm_cvtss_f32(_mm_hadd_ps(s, s));
}

/* acc[0..7] += scale * row[0..63] */
#define AXPY64(acc, scale, row) \
    for (int q = 0; q < 8; ++q) acc[q] = _mm256_fmadd_ps(scale, _mm256_load_ps((row) + 8 * q), acc[q])

static void forward(void) {
#pragma omp parallel for schedule(static)
    for (int n = 0; n < N; ++n) {
        __m256 acc[8];
        for (int q = 0; q < 8; ++q) acc[q] = _mm256_setzero_ps();
        for (int e = n * R; e < (n + 1) * R; ++e) {
            __m256 s = _mm256_broadcast_ss(w + e);
            AXPY64(acc, s, x + (size_t)index_[e] * B);
        }
        for (int q = 0; q < 8; ++q) _mm256_store_ps(y + (size_t)n * B + 8 * q, acc[q]);
    }
}

static void grad_x(void) {
#pragma omp parallel for schedule(static)
    for (int i = 0; i < N_IN; ++i) {
        __m256 acc[8];
        for (int q = 0; q < 8; ++q) acc[q] = _mm256_setzero_ps();
        for (int k = t_offsets[i]; k < t_offsets[i + 1]; ++k) {
            __m256 s = _mm256_broadcast_ss(w + t_entries[k]);
            AXPY64(acc, s, gy + (size_t)t_units[k] * B);
        }
        for (int q = 0; q < 8; ++q) _mm256_store_ps(gx + (size_t)i * B + 8 * q, acc[q]);
    }
}

static void grad_weight_bias(void) {
#pragma omp parallel for schedule(static)
    for (int n = 0; n < N; ++n) {
        const float *g = gy + (size_t)n * B;
        __m256 gv[8], bsum = _mm256_setzero_ps();
        for (int q = 0; q < 8; ++q) {
            gv[q] = _mm256_load_ps(g + 8 * q);
            bsum = _mm256_add_ps(bsum, gv[q]);
        }
        gb[n] = lane_sum(bsum);
        for (int e = n * R; e < (n + 1) * R; ++e) {
            const float *xr = x + (size_t)index_[e] * B;
            __m256 s0 = _mm256_mul_ps(gv[0], _mm256_load_ps(xr));
            __m256 s1 = _mm256_mul_ps(gv[1], _mm256_load_ps(xr + 8));
            for (int q = 2; q < 8; q += 2) {
                s0 = _mm256_fmadd_ps(gv[q], _mm256_load_ps(xr + 8 * q), s0);
                s1 = _mm256_fmadd_ps(gv[q + 1], _mm256_load_ps(xr + 8 * q + 8), s1);
            }
            gw[e] = lane_sum(_mm256_add_ps(s0, s1));
        }
    }
}

static int cmp(const void *a, const void *b) {
    double d = *(const double *)a - *(const double *)b;
    return (d > 0) - (d < 0);
}

enum { FLUSH_BYTES = 64 << 20 };
static char *flush_buf;

static void flush_caches(void) {
#pragma omp parallel for schedule(static)
    for (size_t i = 0; i < FLUSH_BYTES; i += 64) flush_buf[i] = (char)i;
}

static double median(double *t, int n) {
    qsort(t, n, sizeof(double), cmp);
    return t[n / 2];
}

int main(int argc, char **argv) {
    if (argc != 7) {
        fprintf(stderr, "usage: %s DIR N R N_IN THREADS REPEATS\n", argv[0]);
        return 2;
    }
    const char *dir = argv[1];
    N = atoi(argv[2]), R = atoi(argv[3]), N_IN = atoi(argv[4]);
    omp_set_num_threads(atoi(argv[5]));
    int repeats = atoi(argv[6]);
    size_t nr = (size_t)N * R;
    index_ = read_file(dir, "index.bin", 4 * nr);
    t_offsets = read_file(dir, "t_offsets.bin", 4 * (size_t)(N_IN + 1));
    t_entries = read_file(dir, "t_entries.bin", 4 * nr);
    t_units = read_file(dir, "t_units.bin", 4 * nr);
    x = aligned_alloc(64, 4 * (size_t)N_IN * B), gx = aligned_alloc(64, 4 * (size_t)N_IN * B);
    y = aligned_alloc(64, 4 * (size_t)N * B), gy = aligned_alloc(64, 4 * (size_t)N * B);
    w = malloc(4 * nr), gw = malloc(4 * nr), gb = malloc(4 * (size_t)N);
    srand(0);
    for (size_t i = 0; i < (size_t)N_IN * B; ++i) x[i] = rand() / (float)RAND_MAX, gx[i] = 0;
    for (size_t i = 0; i < (size_t)N * B; ++i) gy[i] = rand() / (float)RAND_MAX - 0.5f, y[i] = 0;
    for (size_t i = 0; i < nr; ++i) w[i] = rand() / (float)RAND_MAX - 0.5f;
    flush_buf = malloc(FLUSH_BYTES);
    double *tf = malloc(sizeof(double) * repeats), *tx = malloc(sizeof(double) * repeats);
    double *tw = malloc(sizeof(double) * repeats), *tt = malloc(sizeof(double) * repeats);
    for (int i = -3; i < repeats; ++i) { /* three warm-up rounds */
        flush_caches();
        double t0 = now();
        forward();
        double t1 = now();
        grad_x();
        double t2 = now();
        grad_weight_bias();
        double t3 = now();
        if (i >= 0) tf[i] = 1e3 * (t1 - t0), tx[i] = 1e3 * (t2 - t1), tw[i] = 1e3 * (t3 - t2), tt[i] = 1e3 * (t3 - t0);
    }
    printf("{\"forward\": %.3f, \"grad_x\": %.3f, \"grad_weight_bias\": %.3f, \"forward_backward\": %.3f}\n",
           median(tf, repeats), median(tx, repeats), median(tw, repeats), median(tt, repeats));
    return 0;
}
