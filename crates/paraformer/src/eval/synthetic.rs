//! Seeded synthetic homography pairs from a folder of photos: image 1 is image 0 warped
//! by a random homography (corner perturbation, rotation, scale, translation), so the
//! ground truth is exact. Written as PNGs with a `homographies.txt` list.

use std::io::Write;
use std::path::{Path, PathBuf};

use image::{Rgb, RgbImage};
use nalgebra::Matrix3;

use crate::error::{Error, Result};
use crate::eval::datasets::HomographyPair;
use crate::geometry::homography::{apply, dlt};
use crate::pooling::SplitMix64;

/// How hard the warps are.
#[derive(Debug, Clone, PartialEq)]
pub struct SyntheticConfig {
    /// Pairs to make.
    pub count: usize,
    /// Seed of the warps (pairs are a pure function of it).
    pub seed: u64,
    /// 0 = identity, 1 = strong: corner shifts up to 25% of the size, rotation up to
    /// ±45°, scale 0.7–1.3.
    pub difficulty: f64,
}

impl Default for SyntheticConfig {
    fn default() -> Self {
        Self { count: 200, seed: 0, difficulty: 0.5 }
    }
}

fn uniform(rng: &mut SplitMix64, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * ((rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64)
}

/// A random homography of a `w × h` image onto itself.
pub fn random_homography(w: f64, h: f64, difficulty: f64, rng: &mut SplitMix64) -> Option<Matrix3<f64>> {
    let d = difficulty.clamp(0.0, 1.0);
    let (cx, cy) = (w / 2.0, h / 2.0);
    let angle = uniform(rng, -45.0, 45.0).to_radians() * d;
    let scale = 1.0 + uniform(rng, -0.3, 0.3) * d;
    let (tx, ty) = (uniform(rng, -0.1, 0.1) * w * d, uniform(rng, -0.1, 0.1) * h * d);
    let src = [[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]];
    let dst: Vec<[f64; 2]> = src
        .iter()
        .map(|p| {
            let (x, y) = ((p[0] - cx) * scale, (p[1] - cy) * scale);
            let (xr, yr) = (x * angle.cos() - y * angle.sin(), x * angle.sin() + y * angle.cos());
            let jitter = 0.25 * d;
            [cx + xr + tx + uniform(rng, -jitter, jitter) * w, cy + yr + ty + uniform(rng, -jitter, jitter) * h]
        })
        .collect();
    dlt(&src, &dst)
}

/// Warps `img` by `h` (image → output pixels), bilinear, black outside.
pub fn warp(img: &RgbImage, h: &Matrix3<f64>) -> Option<RgbImage> {
    let hinv = h.try_inverse()?;
    let (w, hh) = img.dimensions();
    let sample = |x: f64, y: f64| -> Rgb<u8> {
        if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f64 && y <= (hh - 1) as f64) {
            return Rgb([0, 0, 0]);
        }
        let (x0, y0) = (x.floor() as u32, y.floor() as u32);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(hh - 1));
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let mut out = [0u8; 3];
        for (c, o) in out.iter_mut().enumerate() {
            let p = |xx, yy| img.get_pixel(xx, yy)[c] as f64;
            let v = p(x0, y0) * (1.0 - fx) * (1.0 - fy) + p(x1, y0) * fx * (1.0 - fy) + p(x0, y1) * (1.0 - fx) * fy + p(x1, y1) * fx * fy;
            *o = v.round().clamp(0.0, 255.0) as u8;
        }
        Rgb(out)
    };
    Some(RgbImage::from_fn(w, hh, |x, y| match apply(&hinv, &[x as f64, y as f64]) {
        Some(p) => sample(p[0], p[1]),
        None => Rgb([0, 0, 0]),
    }))
}

/// Writes `cfg.count` pairs from the photos in `photos` to `out` and returns them.
pub fn generate(photos: &Path, out: &Path, cfg: &SyntheticConfig) -> Result<Vec<HomographyPair>> {
    if !(0.0..=1.0).contains(&cfg.difficulty) {
        return Err(Error::input("difficulty", format!("{}: expected a number from 0 (identity) to 1 (strong)", cfg.difficulty)));
    }
    let io = |p: &Path| {
        let p = p.to_path_buf();
        move |source| Error::Io { path: p, source }
    };
    // Failures to create or write the output are write errors, not read errors.
    let write = |p: &Path| {
        let p = p.to_path_buf();
        move |source| Error::Write { path: p, source }
    };
    let mut files: Vec<PathBuf> = std::fs::read_dir(photos)
        .map_err(io(photos))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| matches!(e.to_string_lossy().to_lowercase().as_str(), "jpg" | "jpeg" | "png" | "pgm" | "ppm")))
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(Error::input(photos.display().to_string(), "no images (jpg, png, pgm, ppm) in the folder"));
    }
    std::fs::create_dir_all(out).map_err(write(out))?;
    let mut rng = SplitMix64::new(cfg.seed);
    let mut pairs = Vec::with_capacity(cfg.count);
    let list_path = out.join("homographies.txt");
    let mut list = std::fs::File::create(&list_path).map_err(write(&list_path))?;
    for i in 0..cfg.count {
        let src = &files[(rng.next_u64() % files.len() as u64) as usize];
        let img = image::open(src).map_err(|e| Error::input(src.display().to_string(), e.to_string()))?.to_rgb8();
        let (w, h) = img.dimensions();
        let hmat = (0..10)
            .find_map(|_| random_homography(w as f64, h as f64, cfg.difficulty, &mut rng))
            .ok_or_else(|| Error::input("difficulty", "could not sample an invertible homography"))?;
        let warped = warp(&img, &hmat).ok_or_else(|| Error::input("difficulty", "singular homography"))?;
        let (n0, n1) = (format!("{i:04}_0.png"), format!("{i:04}_1.png"));
        for (name, im) in [(&n0, &img), (&n1, &warped)] {
            let p = out.join(name);
            im.save(&p).map_err(|e| Error::input(p.display().to_string(), e.to_string()))?;
        }
        let hs: Vec<String> = hmat.transpose().as_slice().iter().map(|v| format!("{v:.12e}")).collect();
        writeln!(list, "{n0} {n1} {}", hs.join(" ")).map_err(write(&list_path))?;
        pairs.push(HomographyPair { name0: n0.clone(), name1: n1.clone(), image0: out.join(&n0), image1: out.join(&n1), h: hmat });
    }
    Ok(pairs)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::datasets::read_homography_list;

    #[test]
    fn warp_moves_pixels_by_the_homography_and_lists_round_trip() {
        let dir = std::env::temp_dir().join(format!("paraformer-synth-{}", std::process::id()));
        let photos = dir.join("photos");
        std::fs::create_dir_all(&photos).expect("tmp");
        // A smooth gradient image, so bilinear sampling is near exact.
        let img = RgbImage::from_fn(120, 90, |x, y| Rgb([(x * 2) as u8, (y * 2) as u8, 100]));
        img.save(photos.join("a.png")).expect("png");
        let pairs = generate(&photos, &dir.join("out"), &SyntheticConfig { count: 3, seed: 7, difficulty: 0.6 }).expect("pairs");
        let listed = read_homography_list(&dir.join("out/homographies.txt")).expect("list");
        assert_eq!(listed.len(), 3);
        for (p, l) in pairs.iter().zip(&listed) {
            assert!((p.h - l.h).abs().max() < 1e-6 * p.h.abs().max());
            let warped = image::open(&p.image1).expect("png").to_rgb8();
            // A pixel of image 0 lands where H sends it, with its colour.
            let q = apply(&p.h, &[60.0, 45.0]).expect("finite");
            let (x, y) = (q[0].round() as u32, q[1].round() as u32);
            if x < 120 && y < 90 {
                let c = warped.get_pixel(x, y);
                assert!((c[0] as i32 - 120).abs() <= 6 && (c[1] as i32 - 90).abs() <= 6, "{c:?} at {x},{y}");
            }
        }
        // Outside 0..=1 the warps leave the documented range (5 gave extreme warps, NaN a
        // misleading "no invertible homography"); an output that cannot be created is a write error.
        for bad in [5.0, -0.1, f64::NAN] {
            let e = generate(&photos, &dir.join("bad"), &SyntheticConfig { count: 1, seed: 0, difficulty: bad }).expect_err("refused").to_string();
            assert!(e.contains("difficulty") && e.contains("0 (identity) to 1"), "{bad}: {e}");
        }
        let e = generate(&photos, &photos.join("a.png").join("out"), &SyntheticConfig { count: 1, ..Default::default() }).expect_err("a file as folder");
        assert!(e.to_string().starts_with("cannot write"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
