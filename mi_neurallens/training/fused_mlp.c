/* A stack of K tanh MLPs of one shape, forward and backward fused per tile of rows: the CPU training step of
 * mi_neurallens.training.fused_cpu (which writes the shape header this file is compiled with, and documents
 * the layout).  Plain C: the compiler vectorises the loops over a layer's outputs (-O3 -march=native), one
 * thread per tile (OpenMP), each thread with its own gradient sums, added at the end.
 *
 * Shape (macros from the header): NIN inputs, NH hidden layers of NW units, NOUT outputs; NL = NH + 1 linear
 * layers.  Parameters P[2l] = W_l (K, a_l, c_l) row-major ("x @ W + b"), P[2l+1] = b_l (K, 1, c_l); their
 * transposes T[l] = W_l^T (K, c_l, a_l), for the backward's input gradients.  Rows: x (K, B, NIN) row-major,
 * acts (K, NH, B, NW) the hidden layers' outputs (after tanh), out (K, B, NOUT).
 *
 * The activation is Eigen's clamped 13/6 rational tanh (mi_neurallens.neural.mlp.tanh_eigen),
 * its derivative 1 - y^2, as in training/stacked.py. */
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <omp.h>

#define NL (NH + 1)
#define TILE 128     /* rows of one map a thread takes at a time: the tile's layers stay in L1/L2 */
#define RB 8         /* rows whose outputs are summed at once (RB x c accumulators in registers) */

static inline float rtanh(float x) {
    x = x < -TANH_CLAMP ? -TANH_CLAMP : (x > TANH_CLAMP ? TANH_CLAMP : x);
    const float x2 = x * x;
    float p = TANH_P6;
    p = p * x2 + TANH_P5; p = p * x2 + TANH_P4; p = p * x2 + TANH_P3;
    p = p * x2 + TANH_P2; p = p * x2 + TANH_P1; p = p * x2 + TANH_P0;
    float q = TANH_Q3;
    q = q * x2 + TANH_Q2; q = q * x2 + TANH_Q1; q = q * x2 + TANH_Q0;
    return x * p / q;
}

/* 16 floats, loaded and stored unaligned: one AVX-512 register (two AVX2 ones) */
typedef float vf __attribute__((vector_size(64), aligned(4), may_alias));
#define VL 16
#define LD(p) (*(const vf *)(p))
#define ST(p, v) (*(vf *)(p) = (v))

/* out[r, :] = (b ? b : 0) + sum_i in[r, i] W[i, :], for n rows; in (n, A) with row stride SA, W (A, C), out
 * (n, C); C = NV * 16.  RB rows at a time: RB x NV sums stay in registers, each W row is loaded once for
 * the RB rows. */
#define DENSE(NAME, A, SA, NV, RB)                                                                     \
static void NAME(int n, const float *restrict in, const float *restrict W, const float *restrict b,   \
                 float *restrict out) {                                                                \
    enum { C = (NV) * VL };                                                                            \
    int r = 0;                                                                                         \
    for (; r + (RB) <= n; r += (RB)) {                                                                 \
        vf acc[RB][NV];                                                                                \
        _Pragma("GCC unroll 32") for (int q = 0; q < (RB); q++)                                        \
            _Pragma("GCC unroll 8") for (int v = 0; v < (NV); v++)                                     \
                acc[q][v] = b ? LD(b + v * VL) : (vf){0};                                              \
        for (int i = 0; i < (A); i++) {                                                                \
            vf w[NV];                                                                                  \
            _Pragma("GCC unroll 8") for (int v = 0; v < (NV); v++) w[v] = LD(W + i * C + v * VL);      \
            _Pragma("GCC unroll 32") for (int q = 0; q < (RB); q++) {                                  \
                const float h = in[(r + q) * (SA) + i];                                                \
                _Pragma("GCC unroll 8") for (int v = 0; v < (NV); v++) acc[q][v] += h * w[v];          \
            }                                                                                          \
        }                                                                                              \
        _Pragma("GCC unroll 32") for (int q = 0; q < (RB); q++)                                        \
            _Pragma("GCC unroll 8") for (int v = 0; v < (NV); v++) ST(out + (r + q) * C + v * VL, acc[q][v]); \
    }                                                                                                  \
    for (; r < n; r++) {                                                                               \
        vf acc[NV];                                                                                    \
        _Pragma("GCC unroll 8") for (int v = 0; v < (NV); v++) acc[v] = b ? LD(b + v * VL) : (vf){0};  \
        for (int i = 0; i < (A); i++) {                                                                \
            const float h = in[r * (SA) + i];                                                          \
            _Pragma("GCC unroll 8") for (int v = 0; v < (NV); v++) acc[v] += h * LD(W + i * C + v * VL); \
        }                                                                                              \
        _Pragma("GCC unroll 8") for (int v = 0; v < (NV); v++) ST(out + r * C + v * VL, acc[v]);       \
    }                                                                                                  \
}

/* dW[i, :] += sum_r in[r, i] d[r, :] and db[:] += sum_r d[r, :], for n rows; in (n, A) with row stride SA,
 * d (n, C), C = NV * 16.  IB (a divisor of A) input units at a time: IB x NV sums in registers. */
#define OUTER(NAME, A, SA, NV, IB)                                                                     \
static void NAME(int n, const float *restrict in, const float *restrict d, float *restrict dW,        \
                 float *restrict db) {                                                                 \
    enum { C = (NV) * VL };                                                                            \
    for (int i0 = 0; i0 < (A); i0 += (IB)) {                                                           \
        vf acc[IB][NV];                                                                                \
        _Pragma("GCC unroll 32") for (int q = 0; q < (IB); q++)                                        \
            _Pragma("GCC unroll 8") for (int v = 0; v < (NV); v++) acc[q][v] = (vf){0};                \
        for (int r = 0; r < n; r++) {                                                                  \
            vf dr[NV];                                                                                 \
            _Pragma("GCC unroll 8") for (int v = 0; v < (NV); v++) dr[v] = LD(d + r * C + v * VL);     \
            _Pragma("GCC unroll 32") for (int q = 0; q < (IB); q++) {                                  \
                const float h = in[r * (SA) + i0 + q];                                                 \
                _Pragma("GCC unroll 8") for (int v = 0; v < (NV); v++) acc[q][v] += h * dr[v];         \
            }                                                                                          \
        }                                                                                              \
        _Pragma("GCC unroll 32") for (int q = 0; q < (IB); q++)                                        \
            _Pragma("GCC unroll 8") for (int v = 0; v < (NV); v++) {                                   \
                float *p = dW + (i0 + q) * C + v * VL;                                                 \
                ST(p, LD(p) + acc[q][v]);                                                              \
            }                                                                                          \
    }                                                                                                  \
    vf s[NV];                                                                                          \
    _Pragma("GCC unroll 8") for (int v = 0; v < (NV); v++) s[v] = (vf){0};                             \
    for (int r = 0; r < n; r++)                                                                        \
        _Pragma("GCC unroll 8") for (int v = 0; v < (NV); v++) s[v] += LD(d + r * C + v * VL);         \
    _Pragma("GCC unroll 8") for (int v = 0; v < (NV); v++) { float *p = db + v * VL; ST(p, LD(p) + s[v]); } \
}

/* NV = NW / 16 vectors a hidden row; the outputs are padded to NVO vectors (NOP floats) in the kernel: the
 * output layer's W and b come padded with zeros (the Python side pads them), out and gout are copied. */
#define NV (NW / VL)
#define NOP (NVO * VL)
DENSE(dense_in, NIN, NIN, NV, RB_H)           /* x -> first hidden layer */
DENSE(dense_hid, NW, NW, NV, RB_H)            /* hidden -> hidden; also d W^T between hidden layers */
DENSE(dense_out, NW, NW, NVO, RB_O)           /* last hidden -> (padded) outputs */
DENSE(dense_back_out, NOUT, NOP, NV, RB_H)    /* d W^T of the output layer */
OUTER(outer_in, NIN, NIN, NV, IB_IN)
OUTER(outer_hid, NW, NW, NV, IB_HID)
OUTER(outer_out, NW, NW, NVO, IB_OUT)

static inline int a_of(int l) { return l == 0 ? NIN : NW; }
static inline int c_of(int l) { return l == NL - 1 ? NOUT : NW; }
static inline int cp_of(int l) { return l == NL - 1 ? NOP : NW; }    /* as the kernel holds it */

/* float offset of layer l's W (a_l x cp_l) and b (cp_l) in one map's block of per-thread sums */
static inline long w_off(int l) {
    long o = 0;
    for (int m = 0; m < l; m++) o += (long)a_of(m) * cp_of(m) + cp_of(m);
    return o;
}

static inline void tanh_rows(int n, float *restrict h) {
    for (int i = 0; i < n * NW; i++) h[i] = rtanh(h[i]);
}

/* Forward of every map on B rows: out (K, B, NOUT); acts (K, NH, B, NW) kept for the backward.  P[2NH] and
 * P[2NH + 1] are the output layer's W (K, NW, NOP) and b (K, 1, NOP), zero-padded. */
void fused_forward(int K, int B, const float *x, const float *const *P, float *acts, float *out) {
    const int tiles = (B + TILE - 1) / TILE;
#pragma omp parallel
    {
        float o[TILE * NOP];
#pragma omp for schedule(static)
        for (int t = 0; t < K * tiles; t++) {
            const int k = t / tiles, r0 = (t % tiles) * TILE, n = B - r0 < TILE ? B - r0 : TILE;
            const float *in = x + ((long)k * B + r0) * NIN;
            for (int l = 0; l < NH; l++) {
                const float *W = P[2 * l] + (long)k * a_of(l) * NW, *b = P[2 * l + 1] + (long)k * NW;
                float *h = acts + (((long)k * NH + l) * B + r0) * NW;
                if (l == 0) dense_in(n, in, W, b, h);
                else dense_hid(n, in, W, b, h);
                tanh_rows(n, h);
                in = h;
            }
            dense_out(n, in, P[2 * NH] + (long)k * NW * NOP, P[2 * NH + 1] + (long)k * NOP, o);
            float *dst = out + ((long)k * B + r0) * NOUT;
            for (int r = 0; r < n; r++)
                for (int j = 0; j < NOUT; j++) dst[r * NOUT + j] = o[r * NOP + j];
        }
    }
}

/* Gradients of sum(gout * out) with respect to every parameter, written to G (laid out as P, unpadded), from
 * the forward's acts.  gout (K, B, NOUT); T[l] = W_l^T (K, c_l, a_l) for l >= 1. */
void fused_backward(int K, int B, const float *x, const float *const *T, const float *acts, const float *gout,
                    float *const *G) {
    const int tiles = (B + TILE - 1) / TILE;
    const long np = w_off(NL);
    const int nth = omp_get_max_threads();
    float *sums = (float *)calloc((size_t)nth * K * np, sizeof(float));
    if (!sums) return;             /* the caller checks G's first value (NaN-filled before the call) */
    /* Each map's tiles are split among the threads the same way whatever K is (one work-sharing loop per map),
     * and the threads' sums are added in thread order: a map's gradient does not depend on the stack around it. */
#pragma omp parallel
    {
        float *mine = sums + (long)omp_get_thread_num() * K * np;
        float go[TILE * NOP], da[TILE * NW], dp[TILE * NW];  /* padded gout; a layer's input and pre-activation gradients */
        for (int i = 0; i < TILE * NOP; i++) go[i] = 0.0f;
        for (int k = 0; k < K; k++) {
#pragma omp for schedule(static) nowait
        for (int tt = 0; tt < tiles; tt++) {
            const int r0 = tt * TILE, n = B - r0 < TILE ? B - r0 : TILE;
            float *g = mine + (long)k * np;
            const float *hk = acts + ((long)k * NH * B + r0) * NW;   /* hidden layer l's output: hk + l * B * NW */
            const float *src = gout + ((long)k * B + r0) * NOUT;
            for (int r = 0; r < n; r++)
                for (int j = 0; j < NOUT; j++) go[r * NOP + j] = src[r * NOUT + j];
            const float *d = go;
            for (int l = NL - 1; l >= 0; l--) {
                const float *in = l == 0 ? x + ((long)k * B + r0) * NIN : hk + (long)(l - 1) * B * NW;
                float *dW = g + w_off(l), *dbl = dW + (long)a_of(l) * cp_of(l);
                if (l == NL - 1) outer_out(n, in, d, dW, dbl);
                else if (l == 0) outer_in(n, in, d, dW, dbl);
                else outer_hid(n, in, d, dW, dbl);
                if (l == 0) break;
                const float *Tl = T[l] + (long)k * a_of(l) * c_of(l);
                if (l == NL - 1) dense_back_out(n, d, Tl, 0, da);
                else dense_hid(n, d, Tl, 0, da);
                const float *h = hk + (long)(l - 1) * B * NW;          /* tanh output feeding layer l */
                for (int i = 0; i < n * NW; i++) dp[i] = da[i] * (1.0f - h[i] * h[i]);
                d = dp;
            }
        }
        }
    }
    /* add the threads' sums into G, unpadded */
    for (int l = 0; l < NL; l++) {
        const int a = a_of(l), c = c_of(l), cp = cp_of(l);
        const long o = w_off(l);
        for (int k = 0; k < K; k++) {
            float *gw = G[2 * l] + (long)k * a * c, *gb = G[2 * l + 1] + (long)k * c;
            for (int i = 0; i < a; i++)
                for (int j = 0; j < c; j++) {
                    float s = 0.0f;
                    for (int th = 0; th < nth; th++) s += sums[((long)th * K + k) * np + o + (long)i * cp + j];
                    gw[i * c + j] = s;
                }
            for (int j = 0; j < c; j++) {
                float s = 0.0f;
                for (int th = 0; th < nth; th++) s += sums[((long)th * K + k) * np + o + (long)a * cp + j];
                gb[j] = s;
            }
        }
    }
    free(sums);
}

void fused_set_threads(int n) { omp_set_num_threads(n); }

/* ---------------------------------------------------------------------------------------------------------------
 * The losses of training/regressor.py and classifier.py, value and gradient with respect to the network's outputs
 * in one pass (what RegressorFit.rows_loss / ClassifierFit.margin_loss compute through some forty PyTorch
 * operations).  Rows are read through strides: a batch is a window of the stacked pools, (K, B, ·) with map
 * stride ks and row stride rs floats.  loss (K) in double; gout (K, B, nout) contiguous.
 * ------------------------------------------------------------------------------------------------------------- */

static inline void dir3(float dx, float dy, float heading, float v[3], float *norm, float *s) {
    const float q = 1.0f - dx * dx - dy * dy;
    *s = sqrtf(q > 1e-8f ? q : 1e-8f);
    v[0] = dx; v[1] = dy; v[2] = heading * *s;
    *norm = sqrtf(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
}

/* The regressor's loss (RegressorFit.rows_loss): weighted standardised MSE of p = out * M against t over the
 * columns `cols` (all five, or 0, 1, 4 with the cosine loss), divided by 5, plus cosine_weight * (2/5) *
 * |dir3(d_pred) - dir3(yraw[2:4])|^2 / (2 sig_d2), each a mean over the rows (weighted by wedge when given).
 * Per map constants, each (K, ·) contiguous: W (5), shift (5), skip (5 x 4), scale (5), sig_d2, wy_c, wy_s,
 * odd_s.  odd: M's odd columns (1 and 3) are (wy_c + wy_s x[2]) / odd_s, else M = 1.  cos_mode: 0 none,
 * 1 the cosine loss (directions left out of the MSE), 2 MSE and cosine. */
void loss_regressor(int K, int B, const float *out,
                    const float *x, long xks, long xrs, const float *t, long tks, long trs,
                    const float *yraw, long yks, long yrs, const float *wedge, long wks, long wrs,
                    const float *W, const float *shift, const float *skip, const float *scale,
                    const float *sig_d2, const float *wy_c, const float *wy_s, const float *odd_s,
                    int odd, int cos_mode, float cosine_weight, float heading, double *loss, float *gout) {
#pragma omp parallel for schedule(static)
    for (int k = 0; k < K; k++) {
        double acc = 0.0;
        const float *Wk = W + 5 * k, *sh = shift + 5 * k, *sk = skip + 5 * NIN * k, *sc = scale + 5 * k;
        const float cos_c = cos_mode ? cosine_weight * 0.4f / (2.0f * sig_d2[k]) : 0.0f;
        for (int r = 0; r < B; r++) {
            const float *xr = x + k * xks + r * xrs, *tr = t + k * tks + r * trs, *o = out + ((long)k * B + r) * 5;
            const float wr = wedge ? wedge[k * wks + r * wrs] : 1.0f;
            float M[5] = {1.0f, 1.0f, 1.0f, 1.0f, 1.0f};
            if (odd) M[1] = M[3] = (wy_c[k] + wy_s[k] * xr[2]) / odd_s[k];
            float p[5], g[5];
            double lr = 0.0;
            for (int j = 0; j < 5; j++) {
                p[j] = o[j] * M[j];
                const int used = cos_mode != 1 || j == 0 || j == 1 || j == 4;
                const float e = p[j] - tr[j];
                lr += used ? (double)(e * e * Wk[j]) / 5.0 : 0.0;
                g[j] = used ? 2.0f * e * Wk[j] / 5.0f : 0.0f;
            }
            if (cos_mode) {
                const float *yr = yraw + k * yks + r * yrs;
                float d[2];
                for (int c = 0; c < 2; c++) {
                    float lin = sh[2 + c];
                    for (int i = 0; i < NIN; i++) lin += xr[i] * sk[(2 + c) * NIN + i];
                    d[c] = M[2 + c] * lin + sc[2 + c] * p[2 + c];
                }
                float a[3], b[3], na, nb, sa, sb;
                dir3(d[0], d[1], heading, a, &na, &sa);
                dir3(yr[2], yr[3], heading, b, &nb, &sb);
                float diff[3], dot = 0.0f, term = 0.0f;
                for (int c = 0; c < 3; c++) {
                    a[c] /= na; b[c] /= nb;
                }
                for (int c = 0; c < 3; c++) {
                    diff[c] = a[c] - b[c];
                    term += diff[c] * diff[c];
                    dot += a[c] * diff[c];
                }
                lr += (double)cos_c * term;
                /* d term / d v = (I - a a^T) 2 (a - b) / |v|; dz/dd = -heading d / s while 1 - |d|^2 > 1e-8 */
                float gv[3];
                for (int c = 0; c < 3; c++) gv[c] = 2.0f * (diff[c] - a[c] * dot) / na;
                const float q = 1.0f - d[0] * d[0] - d[1] * d[1];
                const float dzd = q > 1e-8f ? -heading / sa : 0.0f;
                for (int c = 0; c < 2; c++) g[2 + c] += cos_c * (gv[c] + gv[2] * dzd * d[c]) * sc[2 + c];
            }
            acc += wr * lr;
            float *go = gout + ((long)k * B + r) * 5;
            for (int j = 0; j < 5; j++) go[j] = g[j] * M[j] * wr / (float)B;
        }
        loss[k] = acc / B;
    }
}

/* The classifier's margin interval loss (ClassifierFit.margin_loss): the mean over the rows of relu(lo - z)^2 +
 * relu(z - hi)^2, lo = t unless t <= -clip (then -inf), hi = t unless t >= clip (then +inf); z = out[..., 0]. */
void loss_margin(int K, int B, const float *out, const float *t, long tks, long trs, float clip, double *loss,
                 float *gout) {
#pragma omp parallel for schedule(static)
    for (int k = 0; k < K; k++) {
        double acc = 0.0;
        for (int r = 0; r < B; r++) {
            const float z = out[(long)k * B + r], tr = t[k * tks + r * trs];
            float g = 0.0f;
            if (tr > -clip && z < tr) { acc += (double)(tr - z) * (tr - z); g = -2.0f * (tr - z); }
            if (tr < clip && z > tr) { acc += (double)(z - tr) * (z - tr); g = 2.0f * (z - tr); }
            gout[(long)k * B + r] = g / (float)B;
        }
        loss[k] = acc / B;
    }
}
