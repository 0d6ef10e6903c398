// The interior-point method's KKT solve (jtraj.lq.kkt_directions for several shifts)
// as an XLA FFI kernel on the CPU: the same Riccati recursion, written with the lanes
// (problem x shift) innermost in blocks of W, so that every operation is a loop of W
// independent elementwise products the compiler vectorises. See jtraj/_kkt_native.py.
//
// Inputs per problem (row-major, a leading batch of B problems, contiguous):
//   A (N, nx, nx), B (N, nx, m), Q (N, nx, nx), S (N, m, nx), R (N, m, m),
//   cx (N+1, nx), cu (N, m), PN (nx, nx), shifts (Ls), terminal (nx, r)
// with m = n + 1, nx = 2n + 1 and the recursion's sparsity (jtraj.lq._Recursion):
//   A = [[I, h I, 0], [0, I, 0], [0, 0, 1]], B's v columns diagonal on the q and qd rows.
// Outputs per problem: d (N m, 1 + r, Ls) (z's layout: all v, then all h),
//   dX (N+1, nx, 1 + r, Ls), ok (Ls): whether every stage factorisation was positive
//   definite (d and dX are then finite, NaN otherwise).
// Attribute `ladder`: shift 0 first, the other shifts only for the problems where it is
//   not positive definite; elsewhere their slots are zeros, not positive definite (the
//   caller takes the least shifted positive definite direction: the same one).

#include <cmath>
#include <algorithm>
#include <cstdint>
#include <limits>
#include <vector>

#include "xla/ffi/api/ffi.h"

// JTRAJ_KKT_N: build for that many joints only (a seventh of the compile time); 0: 1 to 7
#ifndef JTRAJ_KKT_N
#define JTRAJ_KKT_N 0
#endif

namespace ffi = xla::ffi;

namespace {


struct Dims {
  int64_t N, n, m, nx, r, R1, Ls;
};

// one block of W lanes (8 or 16: see KktImpl): lane j < cnt solves problem lp[j] with its shift ls[j];
// the dimensions are compile-time (n joints, R1 = 1 + r right-hand sides) and every scratch
// array is a distinct local, so the compiler unrolls the small loops and knows nothing aliases
template <int n, int R1, int W>
void block(const Dims& D, const int64_t* lp, const int64_t* ls, int64_t cnt, const double* A, const double* Bm, const double* Q,
           const double* S, const double* R, const double* cx, const double* cu, const double* PN,
           const double* shifts, const double* term, double* __restrict__ d, double* __restrict__ dX, bool* okout, double* __restrict__ K,
           double* __restrict__ kff) {
  constexpr int m = n + 1, nx = 2 * n + 1, r = R1 - 1;
  const int64_t N = D.N, Ls = D.Ls;
  int64_t prob[W], sh[W];
  for (int j = 0; j < W; ++j) {  // a short block repeats its last lane
    prob[j] = lp[j < cnt ? j : cnt - 1];
    sh[j] = ls[j < cnt ? j : cnt - 1];
  }
  alignas(64) double P[nx * nx * W], p[nx * R1 * W], PA[nx * nx * W], PB[nx * m * W], Quu[m * m * W],
      Qux[m * nx * W], Qxx[nx * nx * W], qu[m * R1 * W], qx[nx * R1 * W], Lc[m * m * W], inv[m * W],
      Z[m * (nx + R1) * W], dx[nx * R1 * W], du[m * R1 * W], h[W], bq[n * W], bqd[n * W], bh[nx * W];
  double sv[W];
  bool ok[W];
  const int64_t szA = N * nx * nx, szB = N * nx * m, szS = N * m * nx, szR = N * m * m;
  const int64_t szcx = (N + 1) * nx, szcu = N * m, szT = nx * r;
#define IX2(a, b, nb) (((a) * (nb) + (b)) * W)
  // stage k's recursion Jacobians by their nonzeros (see the top of the file) into h, bq, bqd, bh
  auto recursion = [&](int64_t k) {
    for (int j = 0; j < W; ++j) {
        const double* Ak = A + prob[j] * szA + k * nx * nx;
        const double* Bk = Bm + prob[j] * szB + k * nx * m;
        h[j] = Ak[0 * nx + n];
        for (int64_t i = 0; i < n; ++i) {
          bq[i * W + j] = Bk[i * m + i];
          bqd[i * W + j] = Bk[(n + i) * m + i];
        }
        for (int64_t a = 0; a < nx; ++a) bh[a * W + j] = Bk[a * m + n];
    }
  };
  for (int j = 0; j < W; ++j) ok[j] = true;
  for (int64_t a = 0; a < nx; ++a) {
    for (int64_t b = 0; b < nx; ++b)
      for (int j = 0; j < W; ++j) P[IX2(a, b, nx) + j] = PN[prob[j] * nx * nx + a * nx + b];
    for (int j = 0; j < W; ++j) p[IX2(a, 0, R1) + j] = cx[prob[j] * szcx + N * nx + a];
    for (int64_t c = 1; c < R1; ++c)
      for (int j = 0; j < W; ++j) p[IX2(a, c, R1) + j] = term[prob[j] * szT + a * r + (c - 1)];
  }
  for (int64_t k = N - 1; k >= 0; --k) {
    recursion(k);
    // PA = P A
    for (int64_t a = 0; a < nx; ++a) {
      for (int64_t b = 0; b < n; ++b)
        for (int j = 0; j < W; ++j) {
          PA[IX2(a, b, nx) + j] = P[IX2(a, b, nx) + j];
          PA[IX2(a, n + b, nx) + j] = P[IX2(a, n + b, nx) + j] + h[j] * P[IX2(a, b, nx) + j];
        }
      for (int j = 0; j < W; ++j) PA[IX2(a, 2 * n, nx) + j] = P[IX2(a, 2 * n, nx) + j];
    }
    // PB = P B
    for (int64_t a = 0; a < nx; ++a) {
      for (int64_t i = 0; i < n; ++i)
        for (int j = 0; j < W; ++j)
          PB[IX2(a, i, m) + j] = P[IX2(a, i, nx) + j] * bq[i * W + j] + P[IX2(a, n + i, nx) + j] * bqd[i * W + j];
      for (int j = 0; j < W; ++j) PB[IX2(a, n, m) + j] = 0.0;
      for (int64_t b = 0; b < nx; ++b)
        for (int j = 0; j < W; ++j) PB[IX2(a, n, m) + j] += P[IX2(a, b, nx) + j] * bh[b * W + j];
    }
    // Quu = R + B^T P B + shift I, Qux = S + B^T PA, qu = cu + B^T p
    for (int64_t i = 0; i < m; ++i) {
      for (int64_t c = 0; c < m; ++c)
        for (int j = 0; j < W; ++j) Quu[IX2(i, c, m) + j] = R[prob[j] * szR + k * m * m + i * m + c];
      for (int64_t c = 0; c < nx; ++c)
        for (int j = 0; j < W; ++j) Qux[IX2(i, c, nx) + j] = S[prob[j] * szS + k * m * nx + i * nx + c];
      for (int j = 0; j < W; ++j) qu[IX2(i, 0, R1) + j] = cu[prob[j] * szcu + k * m + i];
      for (int64_t c = 1; c < R1; ++c)
        for (int j = 0; j < W; ++j) qu[IX2(i, c, R1) + j] = 0.0;
    }
    for (int64_t i = 0; i < n; ++i) {
      for (int64_t c = 0; c < m; ++c)
        for (int j = 0; j < W; ++j)
          Quu[IX2(i, c, m) + j] += bq[i * W + j] * PB[IX2(i, c, m) + j] + bqd[i * W + j] * PB[IX2(n + i, c, m) + j];
      for (int64_t c = 0; c < nx; ++c)
        for (int j = 0; j < W; ++j)
          Qux[IX2(i, c, nx) + j] += bq[i * W + j] * PA[IX2(i, c, nx) + j] + bqd[i * W + j] * PA[IX2(n + i, c, nx) + j];
      for (int64_t c = 0; c < R1; ++c)
        for (int j = 0; j < W; ++j)
          qu[IX2(i, c, R1) + j] += bq[i * W + j] * p[IX2(i, c, R1) + j] + bqd[i * W + j] * p[IX2(n + i, c, R1) + j];
    }
    for (int64_t b = 0; b < nx; ++b) {
      for (int64_t c = 0; c < m; ++c)
        for (int j = 0; j < W; ++j) Quu[IX2(n, c, m) + j] += bh[b * W + j] * PB[IX2(b, c, m) + j];
      for (int64_t c = 0; c < nx; ++c)
        for (int j = 0; j < W; ++j) Qux[IX2(n, c, nx) + j] += bh[b * W + j] * PA[IX2(b, c, nx) + j];
      for (int64_t c = 0; c < R1; ++c)
        for (int j = 0; j < W; ++j) qu[IX2(n, c, R1) + j] += bh[b * W + j] * p[IX2(b, c, R1) + j];
    }
    for (int64_t i = 0; i < m; ++i)
      for (int j = 0; j < W; ++j) Quu[IX2(i, i, m) + j] += shifts[prob[j] * Ls + sh[j]];
    // Qxx = Q + A^T PA, qx = cx + A^T p
    for (int64_t a = 0; a < nx; ++a) {
      for (int64_t c = 0; c < nx; ++c)
        for (int j = 0; j < W; ++j)
          Qxx[IX2(a, c, nx) + j] = Q[prob[j] * szA + k * nx * nx + a * nx + c] + PA[IX2(a, c, nx) + j];
      for (int j = 0; j < W; ++j) qx[IX2(a, 0, R1) + j] = cx[prob[j] * szcx + k * nx + a] + p[IX2(a, 0, R1) + j];
      for (int64_t c = 1; c < R1; ++c)
        for (int j = 0; j < W; ++j) qx[IX2(a, c, R1) + j] = p[IX2(a, c, R1) + j];
    }
    for (int64_t a = 0; a < n; ++a) {
      for (int64_t c = 0; c < nx; ++c)
        for (int j = 0; j < W; ++j) Qxx[IX2(n + a, c, nx) + j] += h[j] * PA[IX2(a, c, nx) + j];
      for (int64_t c = 0; c < R1; ++c)
        for (int j = 0; j < W; ++j) qx[IX2(n + a, c, R1) + j] += h[j] * p[IX2(a, c, R1) + j];
    }
    // Cholesky factorisation of Quu (lower), then Quu X = [Qux | qu] into Z
    for (int64_t c = 0; c < m; ++c) {
      for (int j = 0; j < W; ++j) sv[j] = Quu[IX2(c, c, m) + j];
      for (int64_t t = 0; t < c; ++t)
        for (int j = 0; j < W; ++j) sv[j] -= Lc[IX2(c, t, m) + j] * Lc[IX2(c, t, m) + j];
      for (int j = 0; j < W; ++j) {
        bool pos = sv[j] > 1e-300;
        ok[j] = ok[j] && pos;
        inv[c * W + j] = 1.0 / std::sqrt(pos ? sv[j] : std::numeric_limits<double>::quiet_NaN());
      }
      for (int64_t i = c + 1; i < m; ++i) {
        for (int j = 0; j < W; ++j) Lc[IX2(i, c, m) + j] = Quu[IX2(i, c, m) + j];
        for (int64_t t = 0; t < c; ++t)
          for (int j = 0; j < W; ++j) Lc[IX2(i, c, m) + j] -= Lc[IX2(i, t, m) + j] * Lc[IX2(c, t, m) + j];
        for (int j = 0; j < W; ++j) Lc[IX2(i, c, m) + j] *= inv[c * W + j];
      }
    }
    const int64_t Wd = nx + R1;
    for (int64_t i = 0; i < m; ++i) {
      for (int64_t c = 0; c < nx; ++c)
        for (int j = 0; j < W; ++j) Z[IX2(i, c, Wd) + j] = Qux[IX2(i, c, nx) + j];
      for (int64_t c = 0; c < R1; ++c)
        for (int j = 0; j < W; ++j) Z[IX2(i, nx + c, Wd) + j] = qu[IX2(i, c, R1) + j];
      for (int64_t c = 0; c < Wd; ++c) {
        for (int64_t t = 0; t < i; ++t)
          for (int j = 0; j < W; ++j) Z[IX2(i, c, Wd) + j] -= Lc[IX2(i, t, m) + j] * Z[IX2(t, c, Wd) + j];
        for (int j = 0; j < W; ++j) Z[IX2(i, c, Wd) + j] *= inv[i * W + j];
      }
    }
    for (int64_t i = m - 1; i >= 0; --i)
      for (int64_t c = 0; c < Wd; ++c) {
        for (int64_t t = i + 1; t < m; ++t)
          for (int j = 0; j < W; ++j) Z[IX2(i, c, Wd) + j] -= Lc[IX2(t, i, m) + j] * Z[IX2(t, c, Wd) + j];
        for (int j = 0; j < W; ++j) Z[IX2(i, c, Wd) + j] *= inv[i * W + j];
      }
    double* Kk = K + k * m * nx * W;
    double* kk = kff + k * m * R1 * W;
    for (int64_t i = 0; i < m; ++i) {
      for (int64_t c = 0; c < nx; ++c)
        for (int j = 0; j < W; ++j) Kk[IX2(i, c, nx) + j] = -Z[IX2(i, c, Wd) + j];
      for (int64_t c = 0; c < R1; ++c)
        for (int j = 0; j < W; ++j) kk[IX2(i, c, R1) + j] = -Z[IX2(i, nx + c, Wd) + j];
    }
    // P = sym(Qxx + Qux^T K), p = qx + Qux^T kff
    for (int64_t a = 0; a < nx; ++a) {
      for (int64_t c = 0; c < nx; ++c) {
        for (int j = 0; j < W; ++j) PA[IX2(a, c, nx) + j] = Qxx[IX2(a, c, nx) + j];
        for (int64_t i = 0; i < m; ++i)
          for (int j = 0; j < W; ++j) PA[IX2(a, c, nx) + j] += Qux[IX2(i, a, nx) + j] * Kk[IX2(i, c, nx) + j];
      }
      for (int64_t c = 0; c < R1; ++c) {
        for (int j = 0; j < W; ++j) p[IX2(a, c, R1) + j] = qx[IX2(a, c, R1) + j];
        for (int64_t i = 0; i < m; ++i)
          for (int j = 0; j < W; ++j) p[IX2(a, c, R1) + j] += Qux[IX2(i, a, nx) + j] * kk[IX2(i, c, R1) + j];
      }
    }
    for (int64_t a = 0; a < nx; ++a)
      for (int64_t c = 0; c < nx; ++c)
        for (int j = 0; j < W; ++j) P[IX2(a, c, nx) + j] = 0.5 * (PA[IX2(a, c, nx) + j] + PA[IX2(c, a, nx) + j]);
  }
  // forward: du = K dx + kff, dx <- A dx + B du
  for (int i = 0; i < nx * R1 * W; ++i) dx[i] = 0.0;
  const int64_t nz = N * m;
  const int64_t jmax = cnt;
  auto put_dX = [&](int64_t k) {
    for (int64_t a = 0; a < nx; ++a)
      for (int64_t c = 0; c < R1; ++c)
        for (int64_t j = 0; j < jmax; ++j)
          dX[(((prob[j] * (N + 1) + k) * nx + a) * R1 + c) * Ls + sh[j]] = dx[IX2(a, c, R1) + j];
  };
  for (int64_t k = 0; k < N; ++k) {
    put_dX(k);
    const double* Kk = K + k * m * nx * W;
    const double* kk = kff + k * m * R1 * W;
    for (int64_t i = 0; i < m; ++i)
      for (int64_t c = 0; c < R1; ++c) {
        for (int j = 0; j < W; ++j) du[IX2(i, c, R1) + j] = kk[IX2(i, c, R1) + j];
        for (int64_t b = 0; b < nx; ++b)
          for (int j = 0; j < W; ++j) du[IX2(i, c, R1) + j] += Kk[IX2(i, b, nx) + j] * dx[IX2(b, c, R1) + j];
      }
    recursion(k);
    for (int64_t c = 0; c < R1; ++c) {
      for (int64_t i = 0; i < n; ++i) {
        for (int j = 0; j < W; ++j)
          dx[IX2(i, c, R1) + j] += h[j] * dx[IX2(n + i, c, R1) + j] + bq[i * W + j] * du[IX2(i, c, R1) + j];
        for (int j = 0; j < W; ++j) dx[IX2(n + i, c, R1) + j] += bqd[i * W + j] * du[IX2(i, c, R1) + j];
      }
      for (int64_t a = 0; a < nx; ++a)
        for (int j = 0; j < W; ++j) dx[IX2(a, c, R1) + j] += bh[a * W + j] * du[IX2(n, c, R1) + j];
    }
    for (int64_t c = 0; c < R1; ++c)
      for (int64_t j = 0; j < jmax; ++j) {
        for (int64_t i = 0; i < n; ++i)
          d[((prob[j] * nz + k * n + i) * R1 + c) * Ls + sh[j]] = du[IX2(i, c, R1) + j];
        d[((prob[j] * nz + N * n + k) * R1 + c) * Ls + sh[j]] = du[IX2(n, c, R1) + j];
      }
  }
  put_dX(N);
  for (int64_t j = 0; j < jmax; ++j) okout[prob[j] * Ls + sh[j]] = ok[j];
#undef IX2
}

ffi::Error KktImpl(ffi::Buffer<ffi::F64> A, ffi::Buffer<ffi::F64> Bm, ffi::Buffer<ffi::F64> Q,
                   ffi::Buffer<ffi::F64> S, ffi::Buffer<ffi::F64> R, ffi::Buffer<ffi::F64> cx,
                   ffi::Buffer<ffi::F64> cu, ffi::Buffer<ffi::F64> PN, ffi::Buffer<ffi::F64> shifts,
                   ffi::Buffer<ffi::F64> term, ffi::ResultBuffer<ffi::F64> d, ffi::ResultBuffer<ffi::F64> dX,
                   ffi::ResultBuffer<ffi::PRED> ok, bool ladder) {
  auto bd = Bm.dimensions();
  auto td = term.dimensions();
  auto sd = shifts.dimensions();
  if (bd.size() < 3 || td.size() < 2 || sd.size() < 1)
    return ffi::Error::InvalidArgument("jtraj_kkt: unexpected ranks");
  Dims D;
  D.N = bd[bd.size() - 3];
  D.nx = bd[bd.size() - 2];
  D.m = bd[bd.size() - 1];
  D.n = D.m - 1;
  D.r = td[td.size() - 1];
  D.R1 = D.r + 1;
  D.Ls = sd[sd.size() - 1];
  if (D.nx != 2 * D.n + 1 || td[td.size() - 2] != D.nx)
    return ffi::Error::InvalidArgument("jtraj_kkt: inconsistent shapes");
  const int64_t nb = static_cast<int64_t>(shifts.element_count()) / D.Ls;  // problems
  if (static_cast<int64_t>(Bm.element_count()) != nb * D.N * D.nx * D.m)
    return ffi::Error::InvalidArgument("jtraj_kkt: batch sizes differ");
  // the lanes: every (problem, shift), or with `ladder` shift 0 of every problem first and
  // the others only for the problems where it is not positive definite (the rest: zeros,
  // not positive definite; the caller takes the least shifted positive definite one)
  std::vector<int64_t> lp, ls;
  for (int64_t b = 0; b < nb; ++b)
    for (int64_t s = 0; s < (ladder ? 1 : D.Ls); ++s) {
      lp.push_back(b);
      ls.push_back(s);
    }
  // blocks of 16 lanes, or 8 or 4 for a small call (one problem: 1 lane, then at most 3)
  const int64_t first = ladder ? nb : nb * D.Ls;
  const int W = first <= 4 ? 4 : first <= 8 ? 8 : 16;
  // the gains of one block, kept between calls (a fresh vector of this size, ~140 kB,
  // was zeroed and, above malloc's mmap threshold, page-faulted in on every call)
  static thread_local std::vector<double> work;
  const size_t need = static_cast<size_t>(W * D.N * D.m * (D.nx + D.R1));
  if (work.size() < need) work.resize(need);
  double* K = work.data();
  double* kff = K + W * D.N * D.m * D.nx;
  auto run = [&](auto fn) {
    for (size_t g0 = 0; g0 < lp.size(); g0 += W)
      fn(D, lp.data() + g0, ls.data() + g0, std::min<int64_t>(W, lp.size() - g0), A.typed_data(), Bm.typed_data(),
         Q.typed_data(), S.typed_data(), R.typed_data(), cx.typed_data(), cu.typed_data(), PN.typed_data(),
         shifts.typed_data(), term.typed_data(), d->typed_data(), dX->typed_data(), ok->typed_data(), K, kff);
  };
  auto solve = [&]() -> bool {
    switch (D.n) {
#if JTRAJ_KKT_N == 0 || JTRAJ_KKT_N == 1
      case 1: W == 4 ? run(block<1, 3, 4>) : W == 8 ? run(block<1, 3, 8>) : run(block<1, 3, 16>); break;
#endif
#if JTRAJ_KKT_N == 0 || JTRAJ_KKT_N == 2
      case 2: W == 4 ? run(block<2, 5, 4>) : W == 8 ? run(block<2, 5, 8>) : run(block<2, 5, 16>); break;
#endif
#if JTRAJ_KKT_N == 0 || JTRAJ_KKT_N == 3
      case 3: W == 4 ? run(block<3, 7, 4>) : W == 8 ? run(block<3, 7, 8>) : run(block<3, 7, 16>); break;
#endif
#if JTRAJ_KKT_N == 0 || JTRAJ_KKT_N == 4
      case 4: W == 4 ? run(block<4, 9, 4>) : W == 8 ? run(block<4, 9, 8>) : run(block<4, 9, 16>); break;
#endif
#if JTRAJ_KKT_N == 0 || JTRAJ_KKT_N == 5
      case 5: W == 4 ? run(block<5, 11, 4>) : W == 8 ? run(block<5, 11, 8>) : run(block<5, 11, 16>); break;
#endif
#if JTRAJ_KKT_N == 0 || JTRAJ_KKT_N == 6
      case 6: W == 4 ? run(block<6, 13, 4>) : W == 8 ? run(block<6, 13, 8>) : run(block<6, 13, 16>); break;
#endif
#if JTRAJ_KKT_N == 0 || JTRAJ_KKT_N == 7
      case 7: W == 4 ? run(block<7, 15, 4>) : W == 8 ? run(block<7, 15, 8>) : run(block<7, 15, 16>); break;
#endif
      default: return false;
    }
    return true;
  };
  if (D.R1 != D.nx) return ffi::Error::InvalidArgument("jtraj_kkt: expects 2n terminal rows");
  if (!solve()) return ffi::Error::InvalidArgument("jtraj_kkt: 1 to 7 joints");
  if (ladder && D.Ls > 1) {
    const int64_t nz = D.N * D.m, R1 = D.R1, Ls = D.Ls, nx = D.nx, N = D.N;
    bool* okp = ok->typed_data();
    double* dp = d->typed_data();
    double* dXp = dX->typed_data();
    lp.clear();
    ls.clear();
    for (int64_t b = 0; b < nb; ++b)
      for (int64_t s = 1; s < Ls; ++s) {
        if (okp[b * Ls]) {  // not needed: zeros, not positive definite
          okp[b * Ls + s] = false;
          for (int64_t i = 0; i < nz * R1; ++i) dp[(b * nz * R1 + i) * Ls + s] = 0.0;
          for (int64_t i = 0; i < (N + 1) * nx * R1; ++i) dXp[(b * (N + 1) * nx * R1 + i) * Ls + s] = 0.0;
        } else {
          lp.push_back(b);
          ls.push_back(s);
        }
      }
    if (!lp.empty()) solve();
  }
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(JtrajKkt, KktImpl,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::Buffer<ffi::F64>>()
                                  .Arg<ffi::Buffer<ffi::F64>>()
                                  .Arg<ffi::Buffer<ffi::F64>>()
                                  .Arg<ffi::Buffer<ffi::F64>>()
                                  .Arg<ffi::Buffer<ffi::F64>>()
                                  .Arg<ffi::Buffer<ffi::F64>>()
                                  .Arg<ffi::Buffer<ffi::F64>>()
                                  .Arg<ffi::Buffer<ffi::F64>>()
                                  .Arg<ffi::Buffer<ffi::F64>>()
                                  .Arg<ffi::Buffer<ffi::F64>>()
                                  .Ret<ffi::Buffer<ffi::F64>>()
                                  .Ret<ffi::Buffer<ffi::F64>>()
                                  .Ret<ffi::Buffer<ffi::PRED>>()
                                  .Attr<bool>("ladder"));
