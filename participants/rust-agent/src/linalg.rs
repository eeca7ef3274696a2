//! Small dense linear algebra: row-major f64 matrices of a few dozen rows at most (a 12 × 12
//! satellite block, the joint problem of a `ci` step: 12 m × 12 m for m satellites).
//!
//! Written here rather than taken from a crate so that every loop's order is ours: the
//! per-measurement kernels of the Python filter (numba, `swarmcore/kernels.py`) are
//! repeated loop for loop (their results are then equal bit for bit), and everything else
//! differs from numpy/OpenBLAS only in the order of a product's sums (round-off).

use std::fmt;

#[derive(Clone, PartialEq)]
pub struct Mat {
    pub r: usize,
    pub c: usize,
    pub d: Vec<f64>,
}

impl fmt::Debug for Mat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "Mat {}x{}", self.r, self.c)?;
        for i in 0..self.r {
            writeln!(f, "  {:?}", &self.d[i * self.c..(i + 1) * self.c])?;
        }
        Ok(())
    }
}

/// A matrix that is not positive-definite (Cholesky failed).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NotPd;

impl Mat {
    pub fn zeros(r: usize, c: usize) -> Mat {
        Mat { r, c, d: vec![0.0; r * c] }
    }

    pub fn eye(n: usize) -> Mat {
        let mut m = Mat::zeros(n, n);
        for i in 0..n {
            m.d[i * n + i] = 1.0;
        }
        m
    }

    pub fn from_rows(r: usize, c: usize, d: &[f64]) -> Mat {
        assert_eq!(d.len(), r * c, "from_rows: {} numbers for {r}x{c}", d.len());
        Mat { r, c, d: d.to_vec() }
    }

    pub fn diag(v: &[f64]) -> Mat {
        let mut m = Mat::zeros(v.len(), v.len());
        for (i, x) in v.iter().enumerate() {
            m.d[i * v.len() + i] = *x;
        }
        m
    }

    #[inline]
    pub fn at(&self, i: usize, j: usize) -> f64 {
        self.d[i * self.c + j]
    }

    #[inline]
    pub fn set(&mut self, i: usize, j: usize, v: f64) {
        self.d[i * self.c + j] = v;
    }

    #[inline]
    pub fn add_at(&mut self, i: usize, j: usize, v: f64) {
        self.d[i * self.c + j] += v;
    }

    pub fn diagonal(&self) -> Vec<f64> {
        (0..self.r.min(self.c)).map(|i| self.at(i, i)).collect()
    }

    pub fn t(&self) -> Mat {
        let mut m = Mat::zeros(self.c, self.r);
        for i in 0..self.r {
            for j in 0..self.c {
                m.d[j * self.r + i] = self.d[i * self.c + j];
            }
        }
        m
    }

    /// `self @ b`.
    pub fn mul(&self, b: &Mat) -> Mat {
        assert_eq!(self.c, b.r, "mul: {}x{} @ {}x{}", self.r, self.c, b.r, b.c);
        let mut m = Mat::zeros(self.r, b.c);
        for i in 0..self.r {
            for j in 0..b.c {
                let mut s = 0.0;
                for k in 0..self.c {
                    s += self.d[i * self.c + k] * b.d[k * b.c + j];
                }
                m.d[i * b.c + j] = s;
            }
        }
        m
    }

    /// `self @ bᵀ`.
    pub fn mul_t(&self, b: &Mat) -> Mat {
        assert_eq!(self.c, b.c, "mul_t: {}x{} @ ({}x{})ᵀ", self.r, self.c, b.r, b.c);
        let mut m = Mat::zeros(self.r, b.r);
        for i in 0..self.r {
            for j in 0..b.r {
                let mut s = 0.0;
                for k in 0..self.c {
                    s += self.d[i * self.c + k] * b.d[j * b.c + k];
                }
                m.d[i * b.r + j] = s;
            }
        }
        m
    }

    /// `selfᵀ @ b`.
    pub fn t_mul(&self, b: &Mat) -> Mat {
        assert_eq!(self.r, b.r, "t_mul: ({}x{})ᵀ @ {}x{}", self.r, self.c, b.r, b.c);
        let mut m = Mat::zeros(self.c, b.c);
        for i in 0..self.c {
            for j in 0..b.c {
                let mut s = 0.0;
                for k in 0..self.r {
                    s += self.d[k * self.c + i] * b.d[k * b.c + j];
                }
                m.d[i * b.c + j] = s;
            }
        }
        m
    }

    pub fn mul_vec(&self, v: &[f64]) -> Vec<f64> {
        assert_eq!(self.c, v.len());
        (0..self.r).map(|i| (0..self.c).fold(0.0, |s, k| s + self.d[i * self.c + k] * v[k])).collect()
    }

    pub fn add(&self, b: &Mat) -> Mat {
        assert_eq!((self.r, self.c), (b.r, b.c));
        Mat { r: self.r, c: self.c, d: self.d.iter().zip(&b.d).map(|(x, y)| x + y).collect() }
    }

    pub fn sub(&self, b: &Mat) -> Mat {
        assert_eq!((self.r, self.c), (b.r, b.c));
        Mat { r: self.r, c: self.c, d: self.d.iter().zip(&b.d).map(|(x, y)| x - y).collect() }
    }

    pub fn scale(&self, s: f64) -> Mat {
        Mat { r: self.r, c: self.c, d: self.d.iter().map(|x| x * s).collect() }
    }

    pub fn div(&self, s: f64) -> Mat {
        Mat { r: self.r, c: self.c, d: self.d.iter().map(|x| x / s).collect() }
    }

    /// `0.5 (A + Aᵀ)`.
    pub fn sym(&self) -> Mat {
        assert_eq!(self.r, self.c);
        let n = self.r;
        let mut m = Mat::zeros(n, n);
        for i in 0..n {
            for j in 0..n {
                m.d[i * n + j] = 0.5 * (self.d[i * n + j] + self.d[j * n + i]);
            }
        }
        m
    }

    /// The submatrix of rows `rows` and columns `cols`.
    pub fn take(&self, rows: &[usize], cols: &[usize]) -> Mat {
        let mut m = Mat::zeros(rows.len(), cols.len());
        for (a, &i) in rows.iter().enumerate() {
            for (b, &j) in cols.iter().enumerate() {
                m.d[a * cols.len() + b] = self.at(i, j);
            }
        }
        m
    }

    /// Write `b` at rows `rows`, columns `cols`.
    pub fn put(&mut self, rows: &[usize], cols: &[usize], b: &Mat) {
        assert_eq!((rows.len(), cols.len()), (b.r, b.c));
        for (a, &i) in rows.iter().enumerate() {
            for (c, &j) in cols.iter().enumerate() {
                self.set(i, j, b.d[a * b.c + c]);
            }
        }
    }

    /// The block at (`r0`, `c0`) of `nr` × `nc`.
    pub fn block(&self, r0: usize, c0: usize, nr: usize, nc: usize) -> Mat {
        let mut m = Mat::zeros(nr, nc);
        for i in 0..nr {
            m.d[i * nc..(i + 1) * nc].copy_from_slice(&self.d[(r0 + i) * self.c + c0..(r0 + i) * self.c + c0 + nc]);
        }
        m
    }

    pub fn set_block(&mut self, r0: usize, c0: usize, b: &Mat) {
        for i in 0..b.r {
            let at = (r0 + i) * self.c + c0;
            self.d[at..at + b.c].copy_from_slice(&b.d[i * b.c..(i + 1) * b.c]);
        }
    }

    #[cfg(test)]
    pub fn max_abs(&self) -> f64 {
        self.d.iter().fold(0.0f64, |m, x| m.max(x.abs()))
    }

    /// Lower Cholesky factor (only the lower triangle of `self` is read); the strict upper
    /// triangle of the result is zero.
    pub fn cholesky(&self) -> Result<Mat, NotPd> {
        assert_eq!(self.r, self.c);
        let n = self.r;
        let mut l = Mat::zeros(n, n);
        for j in 0..n {
            let mut s = self.at(j, j);
            for k in 0..j {
                s -= l.at(j, k) * l.at(j, k);
            }
            if !(s > 0.0) {
                return Err(NotPd);
            }
            let ljj = s.sqrt();
            l.set(j, j, ljj);
            for i in j + 1..n {
                let mut t = self.at(i, j);
                for k in 0..j {
                    t -= l.at(i, k) * l.at(j, k);
                }
                l.set(i, j, t / ljj);
            }
        }
        Ok(l)
    }

    /// `log det` of a symmetric positive-definite matrix: twice the sum of the logs of its
    /// Cholesky factor's diagonal, summed as numpy sums (`ci._logdet`).
    pub fn logdet_spd(&self) -> Result<f64, NotPd> {
        let l = self.cholesky()?;
        let logs: Vec<f64> = (0..self.r).map(|i| l.at(i, i).ln()).collect();
        Ok(2.0 * pairwise_sum(&logs))
    }

    /// `L⁻¹ B` for lower-triangular `L = self`.
    pub fn lower_solve(&self, b: &Mat) -> Mat {
        let n = self.r;
        assert_eq!(b.r, n);
        let mut x = b.clone();
        for col in 0..b.c {
            for i in 0..n {
                let mut t = x.at(i, col);
                for k in 0..i {
                    t -= self.at(i, k) * x.at(k, col);
                }
                x.set(i, col, t / self.at(i, i));
            }
        }
        x
    }

    /// `A⁻¹ B` for a general square `A = self` (Gaussian elimination, partial pivoting).
    pub fn solve(&self, b: &Mat) -> Result<Mat, NotPd> {
        let n = self.r;
        assert_eq!((self.c, b.r), (n, n));
        let mut a = self.clone();
        let mut x = b.clone();
        for col in 0..n {
            let mut p = col;
            for i in col + 1..n {
                if a.at(i, col).abs() > a.at(p, col).abs() {
                    p = i;
                }
            }
            if a.at(p, col) == 0.0 || !a.at(p, col).is_finite() {
                return Err(NotPd);
            }
            if p != col {
                for j in 0..n {
                    a.d.swap(p * n + j, col * n + j);
                }
                for j in 0..x.c {
                    x.d.swap(p * x.c + j, col * x.c + j);
                }
            }
            let piv = a.at(col, col);
            for i in col + 1..n {
                let f = a.at(i, col) / piv;
                if f != 0.0 {
                    for j in col..n {
                        let v = a.at(i, j) - f * a.at(col, j);
                        a.set(i, j, v);
                    }
                    for j in 0..x.c {
                        let v = x.at(i, j) - f * x.at(col, j);
                        x.set(i, j, v);
                    }
                }
            }
        }
        for col in 0..x.c {
            for i in (0..n).rev() {
                let mut t = x.at(i, col);
                for k in i + 1..n {
                    t -= a.at(i, k) * x.at(k, col);
                }
                x.set(i, col, t / a.at(i, i));
            }
        }
        Ok(x)
    }
}

/// The sum of `a` in numpy's order (`pairwise_sum` of its add reduction): sequential below
/// 8 numbers, 8 interleaved partial sums up to 128, halves beyond.
pub fn pairwise_sum(a: &[f64]) -> f64 {
    let n = a.len();
    if n < 8 {
        return a.iter().fold(0.0, |s, x| s + x);
    }
    if n <= 128 {
        let mut r = [0.0; 8];
        r.copy_from_slice(&a[..8]);
        let mut i = 8;
        while i < n - n % 8 {
            for j in 0..8 {
                r[j] += a[i + j];
            }
            i += 8;
        }
        let mut res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        while i < n {
            res += a[i];
            i += 1;
        }
        return res;
    }
    let mut n2 = n / 2;
    n2 -= n2 % 8;
    pairwise_sum(&a[..n2]) + pairwise_sum(&a[n2..])
}

/// Eigenvalues (ascending) and eigenvectors (the columns) of a symmetric matrix, by cyclic
/// Jacobi rotations (accurate to round-off; LAPACK's `dsyevd` in numpy's `eigh`).
pub fn eigh(a: &Mat) -> (Vec<f64>, Mat) {
    let n = a.r;
    let mut a = a.sym();
    let mut v = Mat::eye(n);
    for sweep in 0..100 {
        let mut off = 0.0;
        for p in 0..n {
            for q in p + 1..n {
                off += a.at(p, q).abs();
            }
        }
        if off == 0.0 {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = a.at(p, q);
                let (app, aqq) = (a.at(p, p), a.at(q, q));
                let g = 100.0 * apq.abs();
                if sweep > 3 && app.abs() + g == app.abs() && aqq.abs() + g == aqq.abs() {
                    a.set(p, q, 0.0);
                    a.set(q, p, 0.0);
                    continue;
                }
                if apq == 0.0 {
                    continue;
                }
                let theta = 0.5 * (aqq - app) / apq;
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..n {
                    let (akp, akq) = (a.at(k, p), a.at(k, q));
                    a.set(k, p, c * akp - s * akq);
                    a.set(k, q, s * akp + c * akq);
                }
                for k in 0..n {
                    let (apk, aqk) = (a.at(p, k), a.at(q, k));
                    a.set(p, k, c * apk - s * aqk);
                    a.set(q, k, s * apk + c * aqk);
                }
                for k in 0..n {
                    let (vkp, vkq) = (v.at(k, p), v.at(k, q));
                    v.set(k, p, c * vkp - s * vkq);
                    v.set(k, q, s * vkp + c * vkq);
                }
            }
        }
    }
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&i, &j| a.at(i, i).total_cmp(&a.at(j, j)));
    let vals = order.iter().map(|&i| a.at(i, i)).collect();
    let all: Vec<usize> = (0..n).collect();
    (vals, v.take(&all, &order))
}

/// `exp(A)` by scaling and squaring with a Taylor polynomial of degree 12: the algorithm of
/// `swarmcore.linalg.expm_batched` (scale to ‖A/2^s‖₁ ≤ 1/4, Horner, square s times).
pub fn expm(a: &Mat) -> Mat {
    const DEGREE: usize = 12;
    let n = a.r;
    // 1-norm: the largest column sum of |A|.
    let mut norm = 0.0f64;
    for j in 0..n {
        let mut s = 0.0;
        for i in 0..n {
            s += a.at(i, j).abs();
        }
        norm = norm.max(s);
    }
    let s = if norm > 0.25 { ((norm / 0.25).log2().ceil() as i32).max(0) } else { 0 };
    let x = a.div(2f64.powi(s));
    let eye = Mat::eye(n);
    // 1/k! as numpy computes them: 1 / prod(1..k) in floating point.
    let inv_fact: Vec<f64> = (0..=DEGREE).map(|k| 1.0 / (1..=k).fold(1.0f64, |p, i| p * i as f64)).collect();
    let mut e = eye.add(&x.scale(inv_fact[DEGREE] / inv_fact[DEGREE - 1]));
    for k in (1..DEGREE).rev() {
        e = eye.add(&x.mul(&e).div(k as f64));
    }
    for _ in 0..s {
        e = e.mul(&e);
    }
    e
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cholesky_and_solves() {
        let a = Mat::from_rows(3, 3, &[4.0, 2.0, 0.4, 2.0, 5.0, 1.0, 0.4, 1.0, 3.0]);
        let l = a.cholesky().unwrap();
        let back = l.mul_t(&l);
        assert!(back.sub(&a).max_abs() < 1e-14);
        let b = Mat::from_rows(3, 2, &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        let x1 = l.lower_solve(&b);
        let x1 = l.t().solve(&x1).unwrap();
        let x2 = a.solve(&b).unwrap();
        assert!(a.mul(&x1).sub(&b).max_abs() < 1e-13);
        assert!(x1.sub(&x2).max_abs() < 1e-13);
        assert!(
            (a.logdet_spd().unwrap() - (4.0f64 * (5.0 * 3.0 - 1.0) - 2.0 * (2.0 * 3.0 - 0.4) + 0.4 * (2.0 - 5.0 * 0.4)).ln()).abs() < 1e-13
        );
    }

    #[test]
    fn eigh_diagonalises() {
        let a = Mat::from_rows(4, 4, &[4.0, 1.0, 0.5, 0.0, 1.0, 3.0, 0.2, 0.1, 0.5, 0.2, 2.0, 0.3, 0.0, 0.1, 0.3, 1.0]);
        let (w, v) = eigh(&a);
        assert!(w.windows(2).all(|p| p[0] <= p[1]));
        let back = v.mul(&Mat::diag(&w)).mul_t(&v);
        assert!(back.sub(&a).max_abs() < 1e-14, "{back:?}");
        assert!(v.t_mul(&v).sub(&Mat::eye(4)).max_abs() < 1e-14);
    }

    #[test]
    fn sums_as_numpy_does() {
        // numpy: np.array([1e16, 1.0, -1e16, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 3.0]).sum() == 8.0
        let a = [1e16, 1.0, -1e16, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 3.0];
        assert_eq!(pairwise_sum(&a), 8.0);
        assert_eq!(pairwise_sum(&[1.0, 2.0, 3.0]), 6.0);
    }

    #[test]
    fn expm_of_a_rotation_generator() {
        let th = 0.7f64;
        let a = Mat::from_rows(2, 2, &[0.0, -th, th, 0.0]);
        let e = expm(&a);
        let want = Mat::from_rows(2, 2, &[th.cos(), -th.sin(), th.sin(), th.cos()]);
        assert!(e.sub(&want).max_abs() < 1e-15);
    }
}
