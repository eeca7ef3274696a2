//! Bounded scalar minimisation: Brent's method as scipy's `minimize_scalar(method="bounded")`
//! (`scipy.optimize._optimize._minimize_scalar_bounded`, Forsythe–Malcolm–Moler's `fmin`),
//! step for step, so that the same function values lead to the same points.

/// The `x` in `[x1, x2]` minimising `f`, to `xatol` (at most `maxiter` evaluations).
pub fn fminbound(mut f: impl FnMut(f64) -> f64, x1: f64, x2: f64, xatol: f64, maxiter: usize) -> f64 {
    assert!(x1.is_finite() && x2.is_finite() && x1 <= x2, "fminbound: bounds [{x1}, {x2}]");
    let maxfun = maxiter;
    let sqrt_eps = 2.2e-16f64.sqrt();
    let golden_mean = 0.5 * (3.0 - 5.0f64.sqrt());
    let (mut a, mut b) = (x1, x2);
    let mut fulc = a + golden_mean * (b - a);
    let (mut nfc, mut xf) = (fulc, fulc);
    let mut rat = 0.0f64;
    let mut e = 0.0f64;
    let mut x;
    let mut fx = f(xf);
    let mut num = 1;
    let (mut ffulc, mut fnfc) = (fx, fx);
    let mut xm = 0.5 * (a + b);
    let mut tol1 = sqrt_eps * xf.abs() + xatol / 3.0;
    let mut tol2 = 2.0 * tol1;

    while (xf - xm).abs() > (tol2 - 0.5 * (b - a)) {
        let mut golden = true;
        // A parabolic fit?
        if e.abs() > tol1 {
            golden = false;
            let mut r = (xf - nfc) * (fx - ffulc);
            let mut q = (xf - fulc) * (fx - fnfc);
            let mut p = (xf - fulc) * q - (xf - nfc) * r;
            q = 2.0 * (q - r);
            if q > 0.0 {
                p = -p;
            }
            q = q.abs();
            r = e;
            e = rat;
            // Is the parabola acceptable?
            if p.abs() < (0.5 * q * r).abs() && p > q * (a - xf) && p < q * (b - xf) {
                rat = (p + 0.0) / q;
                x = xf + rat;
                if (x - a) < tol2 || (b - x) < tol2 {
                    let si = sign(xm - xf) + if xm - xf == 0.0 { 1.0 } else { 0.0 };
                    rat = tol1 * si;
                }
            } else {
                golden = true;
            }
        }
        if golden {
            e = if xf >= xm { a - xf } else { b - xf };
            rat = golden_mean * e;
        }
        let si = sign(rat) + if rat == 0.0 { 1.0 } else { 0.0 };
        x = xf + si * rat.abs().max(tol1);
        let fu = f(x);
        num += 1;
        if fu <= fx {
            if x >= xf {
                a = xf;
            } else {
                b = xf;
            }
            fulc = nfc;
            ffulc = fnfc;
            nfc = xf;
            fnfc = fx;
            xf = x;
            fx = fu;
        } else {
            if x < xf {
                a = x;
            } else {
                b = x;
            }
            if fu <= fnfc || nfc == xf {
                fulc = nfc;
                ffulc = fnfc;
                nfc = x;
                fnfc = fu;
            } else if fu <= ffulc || fulc == xf || fulc == nfc {
                fulc = x;
                ffulc = fu;
            }
        }
        xm = 0.5 * (a + b);
        tol1 = sqrt_eps * xf.abs() + xatol / 3.0;
        tol2 = 2.0 * tol1;
        if num >= maxfun {
            break;
        }
    }
    xf
}

/// numpy's sign: −1, 0 or 1 (NaN stays NaN).
fn sign(v: f64) -> f64 {
    if v > 0.0 {
        1.0
    } else if v < 0.0 {
        -1.0
    } else if v == 0.0 {
        0.0
    } else {
        f64::NAN
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_a_parabolas_minimum() {
        let x = fminbound(|x| (x - 0.3) * (x - 0.3) + 1.0, 1e-4, 1.0 - 1e-4, 1e-6, 500);
        assert!((x - 0.3).abs() < 1e-6, "{x}");
        // At a bound.
        let x = fminbound(|x| -x, 1e-4, 1.0 - 1e-4, 1e-6, 500);
        assert!((x - (1.0 - 1e-4)).abs() < 1e-5, "{x}");
    }

    /// The points scipy 1.x's `minimize_scalar(f, bounds=(1e-4, 1 - 1e-4), method="bounded",
    /// options={"xatol": 1e-6})` returns for the same functions (Python floats).
    #[test]
    fn equals_scipy_bit_for_bit() {
        let lo = 1e-4;
        let hi = 1.0 - 1e-4;
        let x = fminbound(|x| (x - 0.3) * (x - 0.3) + 1.0, lo, hi, 1e-6, 500);
        assert_eq!(x, 0.3000000000000004);
        let x = fminbound(|x| -x, lo, hi, 1e-6, 500);
        assert_eq!(x, 0.9998994786602725);
        let x = fminbound(|x| (x - 0.71f64).powf(4.0) + 0.1 * x, lo, hi, 1e-6, 500);
        assert_eq!(x, 0.4175981655411766);
    }
}
