//! The agent side of the synthetic camera model (`swarmcore.agent.SyntheticPoseEstimator`):
//! a detection becomes a relative measurement with the covariance the sensor model gives
//! for the measured position (`swarmcore.sensors.relative_noise_cov`).

use crate::filter::{Rel, M6};
use crate::quat::V3;
use crate::scenario::RelativeModel;

/// Body → camera attitude matrices of the six face cameras `+z, +x, +y, −x, −y, −z`
/// (`swarmcore.cameras.T_CB`: rows are the camera axes in body coordinates).
const T_CB: [[[f64; 3]; 3]; 6] = [
    [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]],
    [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
    [[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]],
    [[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]],
    [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]],
];

/// The face camera whose boresight is nearest the line of sight (first on ties).
fn best_camera(r: &V3) -> usize {
    let mut best = 0;
    let mut top = f64::NEG_INFINITY;
    for (c, t) in T_CB.iter().enumerate() {
        let b = &t[2];
        let dot = r[0] * b[0] + r[1] * b[1] + r[2] * b[2];
        if dot > top {
            top = dot;
            best = c;
        }
    }
    best
}

/// `x ** e` as numpy's `ndarray ** scalar` computes it (squares, roots and reciprocals
/// by their own ufuncs).
fn np_pow(x: f64, e: f64) -> f64 {
    if e == 2.0 {
        x * x
    } else if e == 0.5 {
        x.sqrt()
    } else if e == 1.0 {
        x
    } else if e == -1.0 {
        1.0 / x
    } else if e == 0.0 {
        1.0
    } else {
        x.powf(e)
    }
}

/// The noise covariance (6 × 6 in B_i, [attitude, position]) of a relative measurement.
pub fn relative_noise_cov(model: &RelativeModel, r: &V3) -> M6 {
    let mut out = [[0.0; 6]; 6];
    match model {
        RelativeModel::Isotropic { sigma_att, sigma_pos } => {
            for k in 0..3 {
                out[k][k] = sigma_att * sigma_att;
                out[3 + k][3 + k] = sigma_pos * sigma_pos;
            }
        }
        RelativeModel::Camera { sigma_att_c, sigma_pos_c, range_exponent, reference_range } => {
            let range = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
            let scale = np_pow(range / reference_range, *range_exponent);
            let s2 = scale * scale;
            let mut var = [0.0; 6];
            for k in 0..3 {
                var[k] = sigma_att_c[k] * sigma_att_c[k] * s2;
                var[3 + k] = sigma_pos_c[k] * sigma_pos_c[k] * s2;
            }
            // G Σ_C Gᵀ with G = diag(T_BC, T_BC), T_BC = T_CBᵀ (a signed permutation: exact).
            let t = &T_CB[best_camera(r)];
            let mut g = [[0.0; 6]; 6];
            for a in 0..3 {
                for b in 0..3 {
                    g[a][b] = t[b][a];
                    g[3 + a][3 + b] = t[b][a];
                }
            }
            for a in 0..6 {
                for b in 0..6 {
                    let mut s = 0.0;
                    for k in 0..6 {
                        s += g[a][k] * var[k] * g[b][k];
                    }
                    out[a][b] = s;
                }
            }
            for a in 0..6 {
                for b in 0..a {
                    let v = 0.5 * (out[a][b] + out[b][a]);
                    out[a][b] = v;
                    out[b][a] = v;
                }
            }
        }
    }
    out
}

/// One detection of the own cameras: (target, camera, q_BjBi, r_ij_Bi).
#[derive(Clone, Debug)]
pub struct Detection {
    pub target: usize,
    pub camera: u32,
    pub q: [f64; 4],
    pub r: V3,
}

/// The own measurements of a step's detections (those of cameras believed to work).
pub fn measure(model: &RelativeModel, observer: usize, dets: &[Detection]) -> (Vec<Rel>, Vec<u32>) {
    let rel = dets.iter().map(|d| Rel { observer, target: d.target, q: d.q, r: d.r, cov: relative_noise_cov(model, &d.r) }).collect();
    (rel, dets.iter().map(|d| d.camera).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_covariance_is_rotated_into_the_body() {
        let m = RelativeModel::Camera {
            sigma_att_c: [0.03, 0.03, 0.03],
            sigma_pos_c: [0.25, 0.25, 0.12],
            range_exponent: 2.0,
            reference_range: 10.0,
        };
        // Along +x: camera 1, whose boresight (z_C) is body x: the 0.12 σ lands on body x.
        let c = relative_noise_cov(&m, &[10.0, 0.0, 0.0]);
        assert_eq!(c[3][3], 0.12 * 0.12);
        assert_eq!(c[4][4], 0.25 * 0.25);
        assert_eq!(best_camera(&[0.0, 0.0, -3.0]), 5);
    }
}
