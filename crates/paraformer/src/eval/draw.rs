//! Side-by-side match pictures: both images next to each other, inlier matches in
//! green, outliers in red.

use image::{Rgb, RgbImage};

use crate::geometry::Point;

fn line(img: &mut RgbImage, a: Point, b: Point, colour: Rgb<u8>) {
    let steps = (b[0] - a[0]).abs().max((b[1] - a[1]).abs()).ceil().max(1.0) as usize;
    for s in 0..=steps {
        let t = s as f64 / steps as f64;
        let (x, y) = (a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t);
        if x >= 0.0 && y >= 0.0 && (x as u32) < img.width() && (y as u32) < img.height() {
            img.put_pixel(x as u32, y as u32, colour);
        }
    }
}

fn dot(img: &mut RgbImage, p: Point, colour: Rgb<u8>) {
    for dy in -2i64..=2 {
        for dx in -2i64..=2 {
            let (x, y) = (p[0] as i64 + dx, p[1] as i64 + dy);
            if dx * dx + dy * dy <= 4 && x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
                img.put_pixel(x as u32, y as u32, colour);
            }
        }
    }
}

/// The two images side by side with `matches` (`(p0, p1, inlier)`) drawn over them.
pub fn draw_matches(img0: &RgbImage, img1: &RgbImage, matches: &[(Point, Point, bool)]) -> RgbImage {
    let (w0, h0) = img0.dimensions();
    let (w1, h1) = img1.dimensions();
    let mut canvas = RgbImage::from_pixel(w0 + w1, h0.max(h1), Rgb([255, 255, 255]));
    image::imageops::replace(&mut canvas, img0, 0, 0);
    image::imageops::replace(&mut canvas, img1, w0 as i64, 0);
    // Outliers first, so that inliers stay visible on top.
    for pass in [false, true] {
        for &(p0, p1, inlier) in matches.iter().filter(|m| m.2 == pass) {
            let colour = if inlier { Rgb([0, 220, 0]) } else { Rgb([230, 0, 0]) };
            let q1 = [p1[0] + w0 as f64, p1[1]];
            line(&mut canvas, p0, q1, colour);
            dot(&mut canvas, p0, colour);
            dot(&mut canvas, q1, colour);
        }
    }
    canvas
}
