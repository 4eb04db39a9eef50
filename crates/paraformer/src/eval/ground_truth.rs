//! Ground-truth matches from a homography, shared by evaluation and training:
//! `d(i, j) = max(‖H·p0_i − p1_j‖, ‖p0_i − H⁻¹·p1_j‖)`; a pair is positive if the two
//! are mutual nearest neighbours under `d` and `d < threshold`; a keypoint is unmatched
//! if its nearest `d` is above the threshold; otherwise it is ignored.

use nalgebra::Matrix3;

use crate::geometry::homography::apply;
use crate::geometry::Point;

/// Labels per keypoint: `j ≥ 0` matched to keypoint j, [`UNMATCHED`], or [`IGNORED`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GroundTruth {
    /// Label of each keypoint of image 0.
    pub matches0: Vec<i64>,
    /// Label of each keypoint of image 1.
    pub matches1: Vec<i64>,
}

/// The keypoint has no true match (it projects far from every keypoint, or outside).
pub const UNMATCHED: i64 = -1;
/// The keypoint is neither matched nor unmatched (ambiguous), and is left out of the metrics.
pub const IGNORED: i64 = -2;

/// Ground truth for keypoints of two images related by `h` (image 0 → image 1).
#[allow(clippy::needless_range_loop)] // one pass fills the row and the column minima
pub fn matches_from_homography(h: &Matrix3<f64>, kpts0: &[Point], kpts1: &[Point], threshold: f64) -> GroundTruth {
    let (m, n) = (kpts0.len(), kpts1.len());
    let hinv = h.try_inverse();
    let fwd: Vec<Option<Point>> = kpts0.iter().map(|p| apply(h, p)).collect();
    let bwd: Vec<Option<Point>> = kpts1.iter().map(|p| hinv.as_ref().and_then(|hi| apply(hi, p))).collect();
    let dist = |i: usize, j: usize| -> f64 {
        match (fwd[i], bwd[j]) {
            (Some(a), Some(b)) => {
                let (p, q) = (kpts1[j], kpts0[i]);
                (a[0] - p[0]).hypot(a[1] - p[1]).max((b[0] - q[0]).hypot(b[1] - q[1]))
            }
            _ => f64::INFINITY,
        }
    };
    let mut best0 = vec![(f64::INFINITY, usize::MAX); m];
    let mut best1 = vec![(f64::INFINITY, usize::MAX); n];
    for i in 0..m {
        for j in 0..n {
            let d = dist(i, j);
            if d < best0[i].0 {
                best0[i] = (d, j);
            }
            if d < best1[j].0 {
                best1[j] = (d, i);
            }
        }
    }
    let mut gt = GroundTruth { matches0: vec![IGNORED; m], matches1: vec![IGNORED; n] };
    for (i, &(d, j)) in best0.iter().enumerate() {
        if d >= threshold || j == usize::MAX {
            gt.matches0[i] = UNMATCHED;
        } else if best1[j].1 == i {
            gt.matches0[i] = j as i64;
            gt.matches1[j] = i as i64;
        }
    }
    for (j, &(d, _)) in best1.iter().enumerate() {
        if d >= threshold {
            gt.matches1[j] = UNMATCHED;
        }
    }
    gt
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn positives_unmatched_and_ignored() {
        let h = Matrix3::new(1.0, 0.0, 10.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0);
        let k0 = [[0.0, 0.0], [50.0, 50.0], [100.0, 0.0], [200.0, 200.0]];
        // 0 → exact; 1 → 2 px off; 2 → 4 px off (unmatched); 3 → two candidates 1 and 1.5 px away.
        let k1 = [[10.0, 0.0], [62.0, 50.0], [114.0, 0.0], [211.0, 200.0], [210.0, 201.5]];
        let gt = matches_from_homography(&h, &k0, &k1, 3.0);
        assert_eq!(gt.matches0, vec![0, 1, UNMATCHED, 3]);
        // Keypoint 4 of image 1 has a candidate within 3 px that is not mutual: ignored.
        assert_eq!(gt.matches1, vec![0, 1, UNMATCHED, 3, IGNORED]);
    }
}
