/* The dense QP of a linear time-varying MPC problem, condensed onto its inputs (mpc/controllers/dense_qp.py holds
 * the same recursions in numpy, and the definitions).
 *
 * Dynamics x_{k+1} = A_k x_k + B_k u_k + c_k, k = 0..N-1; stage weight W_k = Q (k < N), P (k = N); input weight R.
 * Every array is row-major float64. Outputs:
 *   G  (N+1, nx, n), n = N nu: x_k = G_k u + (free response);
 *   WG (N+1, nx, n): W_k G_k;
 *   H  (n, n): sum_k G_k' W_k G_k plus R on the diagonal blocks (symmetric, both triangles written);
 *   M  (N+1, nx, f) when f > 0: the free response [Phi_k | v_k] (f = nx + 1) or [Phi_k | v_k | Psi_k]
 *      (f = 2 nx + 1), with Phi_{k+1} = A_k Phi_k, v_{k+1} = A_k v_k + c_k, Psi_{k+1} = A_k Psi_k + I.
 * Z (2, nx, n) is scratch. diagonal != 0: Q and P are diagonal (only their diagonals are read).
 *
 * Only the blocks that can be non-zero are multiplied: x_k depends on the inputs before stage k, so G_k has k nu
 * non-zero columns; H's block row k is B_k' Z_{k+1} with Z_N = W_N G_N and Z_k = W_k G_k + A_k' Z_{k+1}, of which
 * the columns of inputs up to k give the lower triangle. */
#include <string.h>

/* out (r x c, leading dimension ldo) += x (r x k) y (k x c) */
static void add_product(int r, int k, int c, const double* x, int ldx, const double* y, int ldy, double* out,
                        int ldo) {
  for (int i = 0; i < r; ++i) {
    double* o = out + i * ldo;
    for (int l = 0; l < k; ++l) {
      const double a = x[i * ldx + l];
      const double* yl = y + l * ldy;
      for (int j = 0; j < c; ++j) o[j] += a * yl[j];
    }
  }
}

/* out (r x c) += x' y with x (k x r) */
static void add_transposed_product(int r, int k, int c, const double* x, int ldx, const double* y, int ldy,
                                   double* out, int ldo) {
  for (int l = 0; l < k; ++l) {
    const double* yl = y + l * ldy;
    for (int i = 0; i < r; ++i) {
      const double a = x[l * ldx + i];
      double* o = out + i * ldo;
      for (int j = 0; j < c; ++j) o[j] += a * yl[j];
    }
  }
}

int pinnmpc_condense(int N, int nx, int nu, const double* A, const double* B, const double* c, const double* Q,
                     const double* P, const double* R, int diagonal, int f, double* G, double* WG, double* H,
                     double* M, double* Z) {
  const int n = N * nu, sg = nx * n, sa = nx * nx;
  if (N < 1 || nx < 1 || nu < 1 || (f != 0 && f != nx + 1 && f != 2 * nx + 1)) return 1;
  memset(G, 0, sizeof(double) * (size_t)(N + 1) * sg);
  memset(WG, 0, sizeof(double) * (size_t)(N + 1) * sg);
  memset(H, 0, sizeof(double) * (size_t)n * n);
  if (f) {
    memset(M, 0, sizeof(double) * (size_t)(N + 1) * nx * f);
    for (int i = 0; i < nx; ++i) M[i * f + i] = 1.0;
  }
  /* forward: G_{k+1} = A_k G_k on the inputs before k, B_k in input k's columns; W_{k+1} G_{k+1}; the free response */
  for (int k = 0; k < N; ++k) {
    const int m = k * nu;
    const double* Ak = A + k * sa;
    double* Gk1 = G + (k + 1) * sg;
    double* WGk1 = WG + (k + 1) * sg;
    const double* W = (k + 1 < N) ? Q : P;
    add_product(nx, nx, m, Ak, nx, G + k * sg, n, Gk1, n);
    for (int i = 0; i < nx; ++i)
      for (int j = 0; j < nu; ++j) Gk1[i * n + m + j] = B[(k * nx + i) * nu + j];
    if (diagonal) {
      for (int i = 0; i < nx; ++i) {
        const double w = W[i * nx + i];
        for (int j = 0; j < m + nu; ++j) WGk1[i * n + j] = w * Gk1[i * n + j];
      }
    } else {
      add_product(nx, nx, m + nu, W, nx, Gk1, n, WGk1, n);
    }
    if (f) {
      double* Mk1 = M + (k + 1) * nx * f;
      add_product(nx, nx, f, Ak, nx, M + k * nx * f, f, Mk1, f);
      for (int i = 0; i < nx; ++i) {
        Mk1[i * f + nx] += c[k * nx + i];
        if (f > nx + 1) Mk1[i * f + nx + 1 + i] += 1.0;
      }
    }
  }
  /* backward: input k's rows of H from Z_{k+1} (inputs 0..k), then Z_k on the inputs before k */
  double* z_next = Z + sg;
  double* z = Z;
  memcpy(z_next, WG + N * sg, sizeof(double) * sg);
  for (int k = N - 1; k >= 0; --k) {
    const int m = k * nu;
    add_transposed_product(nu, nx, m + nu, B + k * nx * nu, nu, z_next, n, H + m * n, n);
    if (k == 0) break;
    for (int i = 0; i < nx; ++i) memcpy(z + i * n, WG + k * sg + i * n, sizeof(double) * m);
    add_transposed_product(nx, nx, m, A + k * sa, nx, z_next, n, z, n);
    double* swap = z;
    z = z_next;
    z_next = swap;
  }
  for (int k = 0; k < N; ++k)
    for (int i = 0; i < nu; ++i)
      for (int j = 0; j < nu; ++j) H[(k * nu + i) * n + k * nu + j] += R[i * nu + j];
  for (int i = 0; i < n; ++i)
    for (int j = i + 1; j < n; ++j) H[i * n + j] = H[j * n + i];
  return 0;
}
