//! Dataset readers and the features file.
//!
//! - HPatches-style folders: `img1..imgN` (any image extension) with `H1toNp` or
//!   `H_1_N` (3×3 ASCII, img1 pixels → imgN pixels); pairs (1, N).
//! - Homography lists (synthetic pairs): `homographies.txt`, one line per pair:
//!   `image0 image1 h00 h01 … h22` (paths relative to the file's folder).
//! - Strecha camera folders: `images/NNNN.jpg` and `gt_dense_cameras/NNNN.jpg.camera`
//!   (K, distortion, R camera→world, centre C, `w h`); pairs of images at most two
//!   apart in the sequence.
//! - SuperGlue's `pairs_with_gt.txt`: `name0 name1 rot0 rot1 K0(9) K1(9) T_0to1(16)`.
//! - Features file: a safetensors file with, per image name, `{name}::keypoints`
//!   `[K, 2]`, `{name}::scores` `[K]`, `{name}::descriptors` `[K, D]`,
//!   `{name}::image_size` `[2]` (width, height), all f32. `paraformer.features.write`
//!   (Python) writes it.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Vector3};
use safetensors::SafeTensors;

use crate::error::{Error, Result};
use crate::features::{features_from_safetensors, Features};

/// Two images related by a homography (image 0 → image 1).
#[derive(Debug, Clone, PartialEq)]
pub struct HomographyPair {
    /// Name of image 0 (file name).
    pub name0: String,
    /// Name of image 1.
    pub name1: String,
    /// Path of image 0.
    pub image0: PathBuf,
    /// Path of image 1.
    pub image1: PathBuf,
    /// Homography mapping pixels of image 0 to image 1.
    pub h: Matrix3<f64>,
}

/// Two calibrated images with their relative pose `x1 = R·x0 + t`.
#[derive(Debug, Clone, PartialEq)]
pub struct PosePair {
    /// Name of image 0 (file name).
    pub name0: String,
    /// Name of image 1.
    pub name1: String,
    /// Path of image 0.
    pub image0: PathBuf,
    /// Path of image 1.
    pub image1: PathBuf,
    /// Intrinsics of image 0.
    pub k0: Matrix3<f64>,
    /// Intrinsics of image 1.
    pub k1: Matrix3<f64>,
    /// Relative rotation `R` (camera 0 → camera 1).
    pub rotation: Matrix3<f64>,
    /// Relative translation `t` (camera 0 → camera 1).
    pub translation: Vector3<f64>,
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> Error + '_ {
    move |source| Error::Io { path: path.to_path_buf(), source }
}

fn numbers(text: &str, path: &Path, expected: usize) -> Result<Vec<f64>> {
    let v: Vec<f64> = text
        .split_whitespace()
        .map(|t| t.parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|e| Error::input(path.display().to_string(), format!("not a number: {e}")))?;
    if v.len() < expected {
        return Err(Error::input(path.display().to_string(), format!("expected {expected} numbers, got {}", v.len())));
    }
    Ok(v)
}

fn mat3(v: &[f64]) -> Matrix3<f64> {
    Matrix3::from_row_slice(&v[..9])
}

fn file_name(p: &Path) -> String {
    p.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default()
}

/// An HPatches-style folder: pairs (img1, imgN) with their homographies.
pub fn read_hpatches_folder(dir: &Path) -> Result<Vec<HomographyPair>> {
    let mut images: BTreeMap<usize, PathBuf> = BTreeMap::new();
    for entry in std::fs::read_dir(dir).map_err(io(dir))? {
        let path = entry.map_err(io(dir))?.path();
        let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        if let Some(k) = stem.strip_prefix("img").and_then(|n| n.parse::<usize>().ok()) {
            images.insert(k, path);
        }
    }
    let first = images.get(&1).ok_or_else(|| Error::input(dir.display().to_string(), "no img1.* in the folder"))?;
    let mut pairs = Vec::new();
    for (&k, path) in images.range(2..) {
        let h_file = [format!("H1to{k}p"), format!("H_1_{k}")].into_iter().map(|n| dir.join(n)).find(|p| p.exists());
        let Some(h_file) = h_file else { continue };
        let text = std::fs::read_to_string(&h_file).map_err(io(&h_file))?;
        pairs.push(HomographyPair {
            name0: file_name(first),
            name1: file_name(path),
            image0: first.clone(),
            image1: path.clone(),
            h: mat3(&numbers(&text, &h_file, 9)?),
        });
    }
    Ok(pairs)
}

/// A homography list file (`image0 image1 h00 … h22` per line).
pub fn read_homography_list(file: &Path) -> Result<Vec<HomographyPair>> {
    let dir = file.parent().unwrap_or(Path::new("."));
    let text = std::fs::read_to_string(file).map_err(io(file))?;
    text.lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .map(|line| {
            let mut parts = line.split_whitespace();
            let (a, b) = (parts.next().unwrap_or_default(), parts.next().unwrap_or_default());
            let rest: Vec<&str> = parts.collect();
            let h = numbers(&rest.join(" "), file, 9)?;
            Ok(HomographyPair { name0: a.into(), name1: b.into(), image0: dir.join(a), image1: dir.join(b), h: mat3(&h) })
        })
        .collect()
}

/// A Strecha-format scene: pairs of images at most `max_gap` apart.
pub fn read_strecha(dir: &Path, max_gap: usize) -> Result<Vec<PosePair>> {
    let cams = dir.join("gt_dense_cameras");
    let mut names: Vec<String> = std::fs::read_dir(&cams)
        .map_err(io(&cams))?
        .filter_map(|e| e.ok().map(|e| file_name(&e.path())))
        .filter_map(|n| n.strip_suffix(".camera").map(str::to_string))
        .collect();
    names.sort();
    let read_cam = |name: &str| -> Result<(Matrix3<f64>, Matrix3<f64>, Vector3<f64>)> {
        let p = cams.join(format!("{name}.camera"));
        let v = numbers(&std::fs::read_to_string(&p).map_err(io(&p))?, &p, 24)?;
        // K (9), distortion (3), R camera→world (9), centre C (3).
        let k = mat3(&v[0..9]);
        let r_cw = mat3(&v[12..21]);
        let c = Vector3::new(v[21], v[22], v[23]);
        // World → camera: x_c = Rᵀ(X − C).
        Ok((k, r_cw.transpose(), -(r_cw.transpose() * c)))
    };
    let cams_all = names.iter().map(|n| read_cam(n)).collect::<Result<Vec<_>>>()?;
    let mut pairs = Vec::new();
    for i in 0..names.len() {
        for j in i + 1..names.len().min(i + 1 + max_gap) {
            let ((k0, r0, t0), (k1, r1, t1)) = (&cams_all[i], &cams_all[j]);
            let rotation = r1 * r0.transpose();
            pairs.push(PosePair {
                name0: names[i].clone(),
                name1: names[j].clone(),
                image0: dir.join("images").join(&names[i]),
                image1: dir.join("images").join(&names[j]),
                k0: *k0,
                k1: *k1,
                rotation,
                translation: t1 - rotation * t0,
            });
        }
    }
    Ok(pairs)
}

/// SuperGlue's `pairs_with_gt.txt`; images are looked up in `image_dir`.
pub fn read_pairs_with_gt(file: &Path, image_dir: &Path) -> Result<Vec<PosePair>> {
    let text = std::fs::read_to_string(file).map_err(io(file))?;
    text.lines()
        .filter(|l| !l.trim().is_empty())
        .map(|line| {
            let parts: Vec<&str> = line.split_whitespace().collect();
            if parts.len() < 38 {
                return Err(Error::input(file.display().to_string(), format!("expected 38 fields per line, got {}", parts.len())));
            }
            let v = numbers(&parts[4..].join(" "), file, 34)?;
            let t = Matrix3::from_row_slice(&[v[18], v[19], v[20], v[22], v[23], v[24], v[26], v[27], v[28]]);
            Ok(PosePair {
                name0: parts[0].into(),
                name1: parts[1].into(),
                image0: image_dir.join(parts[0]),
                image1: image_dir.join(parts[1]),
                k0: mat3(&v[0..9]),
                k1: mat3(&v[9..18]),
                rotation: t,
                translation: Vector3::new(v[21], v[25], v[29]),
            })
        })
        .collect()
}

/// Reads a features file into a map from image name to features.
pub fn read_features(path: &Path) -> Result<BTreeMap<String, Features>> {
    let bytes = std::fs::read(path).map_err(io(path))?;
    let st = SafeTensors::deserialize(&bytes).map_err(|e| Error::WeightsFormat(e.to_string()))?;
    let mut out = BTreeMap::new();
    for name in st.names() {
        let Some(image) = name.strip_suffix("::keypoints") else { continue };
        let f = features_from_safetensors(&st, |field| format!("{image}::{field}"))?;
        f.validate(f.descriptor_dim, 0).map_err(|e| Error::input(image, e.to_string()))?;
        out.insert(image.to_string(), f);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shared(rel: &str) -> Option<PathBuf> {
        let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data").join(rel);
        if p.exists() {
            Some(p)
        } else {
            println!("skipped: {} is absent", p.display());
            None
        }
    }

    #[test]
    fn reads_the_shared_datasets_when_present() {
        if let Some(d) = shared("homography/iguazu_noise") {
            let pairs = read_hpatches_folder(&d).expect("hpatches folder");
            assert_eq!(pairs.len(), 5);
            assert!((pairs[0].h - Matrix3::identity()).abs().max() < 1e-12);
        }
        if let Some(d) = shared("pose/strecha_entry-P10") {
            let pairs = read_strecha(&d, 2).expect("strecha");
            assert_eq!(pairs.len(), 17);
            let r = pairs[0].rotation;
            assert!(((r * r.transpose()) - Matrix3::identity()).abs().max() < 1e-4);
        }
        if let Some(d) = shared("pose/scannet_sample") {
            let pairs = read_pairs_with_gt(&d.join("pairs_with_gt.txt"), &d).expect("pairs");
            assert_eq!(pairs.len(), 15);
        }
    }
}
