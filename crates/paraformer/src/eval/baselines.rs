//! Descriptor-matching baselines on the same features: nearest neighbour, mutual
//! nearest neighbour, and Lowe's ratio test (Euclidean descriptor distance).

use crate::kernels::{Ctx, View};

/// Squared Euclidean distances `[M, N]` between rows of `d0` `[M, D]` and `d1` `[N, D]`,
/// as `|a|² + |b|² − 2·a·b` with one GEMM (clamped at 0 against rounding).
fn distances(d0: &[f32], d1: &[f32], dim: usize) -> Vec<f32> {
    let (m, n) = (d0.len() / dim.max(1), d1.len() / dim.max(1));
    let mut out = vec![0.0f32; m * n];
    let sq = |d: &[f32]| d.chunks_exact(dim.max(1)).map(|r| r.iter().map(|v| v * v).sum::<f32>()).collect::<Vec<f32>>();
    let (s0, s1) = (sq(d0), sq(d1));
    let a = View { data: d0, rows: m, cols: dim, stride: dim };
    let b = View { data: d1, rows: n, cols: dim, stride: dim };
    if Ctx::default().gemm(&mut out, n, a, false, b, true, -2.0, false, true).is_err() {
        // Unreachable with consistent shapes; keep an exact fallback rather than panic.
        for i in 0..m {
            for j in 0..n {
                out[i * n + j] = -2.0 * d0[i * dim..(i + 1) * dim].iter().zip(&d1[j * dim..(j + 1) * dim]).map(|(x, y)| x * y).sum::<f32>();
            }
        }
    }
    for (row, a2) in out.chunks_exact_mut(n.max(1)).zip(&s0) {
        for (v, b2) in row.iter_mut().zip(&s1) {
            *v = (*v + a2 + b2).max(0.0);
        }
    }
    out
}

/// Which baseline.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Baseline {
    /// Each keypoint of image 0 to its nearest descriptor in image 1.
    NearestNeighbour,
    /// Nearest neighbours both ways that agree.
    MutualNearestNeighbour,
    /// Keep matches whose best distance is below `ratio` × the second best.
    RatioTest {
        /// Lowe's ratio (0.8 is usual).
        ratio: f32,
    },
}

impl Baseline {
    /// The methods' names, as [`Baseline::from_method`] and [`Baseline::parse`] take them.
    pub const NAMES: [&'static str; 3] = ["mnn", "nn", "ratio"];

    /// Lowe's usual ratio, where `ratio` is named without one.
    pub const DEFAULT_RATIO: f32 = 0.8;

    /// The baseline `method` (one of [`Baseline::NAMES`]); `ratio` is read by `ratio` only.
    pub fn from_method(method: &str, ratio: f32) -> crate::Result<Self> {
        match method {
            "nn" => Ok(Baseline::NearestNeighbour),
            "mnn" => Ok(Baseline::MutualNearestNeighbour),
            "ratio" => Baseline::ratio_test(ratio),
            other => Err(crate::Error::input("method", format!("{other:?}: expected one of {}", Baseline::NAMES.join(", ")))),
        }
    }

    /// The method's name in [`Baseline::NAMES`].
    pub fn name(&self) -> &'static str {
        match self {
            Baseline::NearestNeighbour => "nn",
            Baseline::MutualNearestNeighbour => "mnn",
            Baseline::RatioTest { .. } => "ratio",
        }
    }

    /// The ratio of a ratio test, [`Baseline::DEFAULT_RATIO`] for the other methods.
    pub fn ratio(&self) -> f32 {
        match self {
            Baseline::RatioTest { ratio } => *ratio,
            _ => Baseline::DEFAULT_RATIO,
        }
    }

    /// `nn`, `mnn`, `ratio` (Lowe's 0.8) or `ratio:R`; `None` for any other name, an error
    /// for a ratio that is not a number in (0, 1].
    pub fn parse(spec: &str) -> crate::Result<Option<Self>> {
        let (method, ratio) = match spec.split_once(':') {
            None => (spec, Baseline::DEFAULT_RATIO),
            Some(("ratio", r)) => ("ratio", r.parse().map_err(|e| crate::Error::input("matcher", format!("`{spec}`: {e}")))?),
            Some(_) => return Ok(None),
        };
        if !Baseline::NAMES.contains(&method) {
            return Ok(None);
        }
        Baseline::from_method(method, ratio).map(Some)
    }

    /// Lowe's ratio test at `ratio`: finite, above 0 and at most 1 (a best distance is never
    /// above the second best, so 1 keeps every nearest neighbour and 0 or less none).
    pub fn ratio_test(ratio: f32) -> crate::Result<Self> {
        if ratio.is_finite() && ratio > 0.0 && ratio <= 1.0 {
            Ok(Baseline::RatioTest { ratio })
        } else {
            Err(crate::Error::input("ratio", format!("{ratio}: expected a number in (0, 1], e.g. 0.8")))
        }
    }
}

/// `matches0` `[M]` (−1 = unmatched) by a baseline.
pub fn match_descriptors(d0: &[f32], d1: &[f32], dim: usize, method: Baseline) -> Vec<i64> {
    let (m, n) = (d0.len() / dim.max(1), d1.len() / dim.max(1));
    if m == 0 || n == 0 {
        return vec![-1; m];
    }
    let dist = distances(d0, d1, dim);
    let nn0: Vec<(usize, f32, f32)> = (0..m)
        .map(|i| {
            let row = &dist[i * n..(i + 1) * n];
            let (mut b, mut bd, mut sd) = (0, f32::INFINITY, f32::INFINITY);
            for (j, &d) in row.iter().enumerate() {
                if d < bd {
                    (sd, bd, b) = (bd, d, j);
                } else if d < sd {
                    sd = d;
                }
            }
            (b, bd, sd)
        })
        .collect();
    match method {
        Baseline::NearestNeighbour => nn0.iter().map(|&(j, _, _)| j as i64).collect(),
        Baseline::MutualNearestNeighbour => {
            // Column minima in one row-major pass (first index wins ties, like argmin).
            let mut nn1 = vec![(f32::INFINITY, 0usize); n];
            for (i, row) in dist.chunks_exact(n).enumerate() {
                for (best, &d) in nn1.iter_mut().zip(row) {
                    if d < best.0 {
                        *best = (d, i);
                    }
                }
            }
            let nn1: Vec<usize> = nn1.into_iter().map(|b| b.1).collect();
            nn0.iter().enumerate().map(|(i, &(j, _, _))| if nn1[j] == i { j as i64 } else { -1 }).collect()
        }
        Baseline::RatioTest { ratio } => nn0
            .iter()
            .map(|&(j, bd, sd)| if bd.sqrt() < ratio * sd.sqrt() { j as i64 } else { -1 })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn baselines_on_a_small_example() {
        // d0 rows: (0,0), (1,0), (5,5); d1 rows: (0.1,0), (0.9,0), (5,4).
        let d0 = [0.0, 0.0, 1.0, 0.0, 5.0, 5.0];
        let d1 = [0.1, 0.0, 0.9, 0.0, 5.0, 4.0, 0.2, 0.0];
        assert_eq!(match_descriptors(&d0, &d1, 2, Baseline::NearestNeighbour), vec![0, 1, 2]);
        // d1 row 3 (0.2, 0) is nearer to d0 row 0 than row 0 of d1 is? no: 0.1 < 0.2 — mutual holds.
        assert_eq!(match_descriptors(&d0, &d1, 2, Baseline::MutualNearestNeighbour), vec![0, 1, 2]);
        // Row 0: best 0.1, second 0.2 → ratio 0.5 < 0.8 kept; row 1: 0.1 vs 0.8 kept; row 2 kept.
        assert_eq!(match_descriptors(&d0, &d1, 2, Baseline::RatioTest { ratio: 0.4 }), vec![-1, 1, 2]);
        assert_eq!(match_descriptors(&[], &d1, 2, Baseline::NearestNeighbour), Vec::<i64>::new());
    }

    #[test]
    fn ratio_outside_zero_to_one_is_refused_by_name() {
        assert_eq!(Baseline::ratio_test(0.8).ok(), Some(Baseline::RatioTest { ratio: 0.8 }));
        assert!(Baseline::ratio_test(1.0).is_ok());
        for bad in [0.0, -1.0, 1.5, f32::NAN, f32::INFINITY] {
            let e = Baseline::ratio_test(bad).expect_err("refused").to_string();
            assert!(e.contains("ratio") && e.contains("(0, 1]"), "{bad}: {e}");
        }
    }

    #[test]
    fn names_parse_to_baselines() {
        let parse = |s: &str| Baseline::parse(s).expect(s);
        assert_eq!(parse("nn"), Some(Baseline::NearestNeighbour));
        assert_eq!(parse("mnn"), Some(Baseline::MutualNearestNeighbour));
        assert_eq!(parse("ratio"), Some(Baseline::RatioTest { ratio: 0.8 }));
        assert_eq!(parse("ratio:0.7"), Some(Baseline::RatioTest { ratio: 0.7 }));
        assert_eq!(parse("nn:3"), None);
        assert_eq!(parse("weights.safetensors"), None);
        assert!(Baseline::parse("ratio:x").expect_err("not a number").to_string().contains("`ratio:x`"));
        assert!(Baseline::parse("ratio:2").expect_err("above 1").to_string().contains("(0, 1]"));
    }

    #[test]
    fn methods_round_trip_through_their_names() {
        for name in Baseline::NAMES {
            let b = Baseline::from_method(name, 0.6).expect(name);
            assert_eq!((b.name(), Baseline::parse(name).expect(name).map(|p| p.name())), (name, Some(name)));
        }
        assert_eq!(Baseline::from_method("ratio", 0.6).map(|b| b.ratio()).ok(), Some(0.6));
        assert_eq!(Baseline::from_method("mnn", 0.6).map(|b| b.ratio()).ok(), Some(Baseline::DEFAULT_RATIO));
        let e = Baseline::from_method("lowe", 0.8).expect_err("unknown").to_string();
        assert!(e.contains("method") && e.contains("\"lowe\"") && e.contains("mnn, nn, ratio"), "{e}");
    }
}
