//! The bf16 matrix product of the attention layers' Linear layers (`Precision::Bf16`):
//! `dst += x·W` with `x` and `W` rounded to bf16 and fp32 accumulation (`vdpbf16ps`),
//! on CPUs with AVX-512 BF16. `W` is packed once per layer, in pairs of rows
//! (`[in/2][out][2]`), the layout the instruction reads.

#[cfg(target_arch = "x86_64")]
pub use x86::{gemm_acc, pack_weights};

/// Whether this CPU runs [`gemm_acc`].
pub fn available() -> bool {
    crate::attention_fused::bf16_available()
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    use rayon::prelude::*;

    use crate::error::Result;
    use crate::kernels::{internal, to_bf16, SharedMut, View};

    /// Rows per register tile, and per parallel task.
    const TILE: usize = 8;
    const BLOCK: usize = 64;


    /// `wt` `[k, n]` row-major → `[ceil(k/2)][n_pad][2]` bf16, `n_pad` = `n` rounded up to 16.
    pub fn pack_weights(wt: &[f32], k: usize, n: usize) -> Vec<u16> {
        let np = n.div_ceil(16) * 16;
        let mut out = vec![0u16; k.div_ceil(2) * np * 2];
        for i in 0..k {
            for (j, &w) in wt[i * n..(i + 1) * n].iter().enumerate() {
                out[(i / 2) * np * 2 + j * 2 + i % 2] = to_bf16(w);
            }
        }
        out
    }

    /// `dst[r][..c1−c0] += x[r]·W[:, c0..c1]` for every row of `x` (`[m, k]`), with `wp` from
    /// [`pack_weights`] of a `[k, n]` matrix; `c0` a multiple of 16. An error where this CPU
    /// lacks AVX-512 BF16 ([`super::available`]).
    #[allow(clippy::too_many_arguments)]
    pub fn gemm_acc(dst: &mut [f32], dst_stride: usize, x: View, wp: &[u16], k: usize, n: usize, c0: usize, c1: usize) -> Result<()> {
        let m = x.rows;
        let np = n.div_ceil(16) * 16;
        let k2 = k.div_ceil(2);
        if x.cols != k || !c0.is_multiple_of(16) || c1 > n || c0 > c1 || wp.len() != k2 * np * 2 || !super::available() {
            return Err(internal(format!("bf16 gemm x {m}×{} with W {k}×{n} columns {c0}..{c1}", x.cols)));
        }
        if m == 0 || c0 == c1 {
            return Ok(());
        }
        if (m - 1) * dst_stride + (c1 - c0) > dst.len() || (m - 1) * x.stride + k > x.data.len() {
            return Err(internal(format!("bf16 gemm output {m}×{} (stride {dst_stride}) in {} values", c1 - c0, dst.len())));
        }
        let out = SharedMut(dst.as_mut_ptr());
        (0..m.div_ceil(BLOCK)).into_par_iter().for_each(|b| {
            let (r0, r1) = (b * BLOCK, ((b + 1) * BLOCK).min(m));
            // The block's rows as bf16 pairs, padded with zero rows to whole tiles.
            let rows = (r1 - r0).div_ceil(TILE) * TILE;
            let mut a = vec![0u16; rows * k2 * 2];
            for r in r0..r1 {
                let dst_row = &mut a[(r - r0) * k2 * 2..];
                for (t, &v) in x.row(r).iter().enumerate() {
                    dst_row[t] = to_bf16(v);
                }
            }
            // SAFETY: AVX-512 BF16 was checked on entry; block b alone writes rows
            // r0..r1 of `dst`, inside the bounds checked above.
            unsafe { block(&a, r1 - r0, k2, wp, np, c0, c1, out.at(r0 * dst_stride), dst_stride) };
        });
        Ok(())
    }

    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    unsafe fn block(a: &[u16], rows: usize, k2: usize, wp: &[u16], np: usize, c0: usize, c1: usize, dst: *mut f32, ld: usize) {
        for j0 in (c0..c1).step_by(32) {
            let (m0, m1) = (lanes(c1, j0), lanes(c1, j0 + 16));
            for t0 in (0..rows).step_by(TILE) {
                let mut acc = [[_mm512_setzero_ps(); 2]; TILE];
                let ap = a.as_ptr().add(t0 * k2 * 2);
                for p in 0..k2 {
                    let wrow = wp.as_ptr().add(p * np * 2 + j0 * 2);
                    let b0 = std::mem::transmute::<__m512i, __m512bh>(_mm512_loadu_si512(wrow as *const _));
                    // The second half may lie past `np` when c1 − j0 ≤ 16: read it only when used.
                    let b1 = if m1 != 0 {
                        std::mem::transmute::<__m512i, __m512bh>(_mm512_loadu_si512(wrow.add(32) as *const _))
                    } else {
                        std::mem::transmute::<__m512i, __m512bh>(_mm512_setzero_si512())
                    };
                    for (r, acc_r) in acc.iter_mut().enumerate() {
                        let pair = (ap.add(r * k2 * 2 + 2 * p) as *const i32).read_unaligned();
                        let x = std::mem::transmute::<__m512i, __m512bh>(_mm512_set1_epi32(pair));
                        acc_r[0] = _mm512_dpbf16_ps(acc_r[0], x, b0);
                        acc_r[1] = _mm512_dpbf16_ps(acc_r[1], x, b1);
                    }
                }
                for (r, acc_r) in acc.iter().enumerate().take(rows.saturating_sub(t0).min(TILE)) {
                    let d = dst.add((t0 + r) * ld + (j0 - c0));
                    _mm512_mask_storeu_ps(d, m0, _mm512_add_ps(_mm512_maskz_loadu_ps(m0, d), acc_r[0]));
                    _mm512_mask_storeu_ps(d.add(16), m1, _mm512_add_ps(_mm512_maskz_loadu_ps(m1, d.add(16)), acc_r[1]));
                }
            }
        }
    }

    /// Lanes `j0..j0+16` below `end`.
    fn lanes(end: usize, j0: usize) -> __mmask16 {
        if end >= j0 + 16 {
            0xFFFF
        } else if end <= j0 {
            0
        } else {
            ((1u32 << (end - j0)) - 1) as __mmask16
        }
    }

    #[cfg(test)]
    mod tests {
        use super::*;
        use crate::kernels::{Ctx, Matrix};

        #[test]
        fn bf16_gemm_matches_fp32_within_bf16_rounding() {
            if !super::super::available() {
                eprintln!("skipped: no AVX-512 BF16 here");
                return;
            }
            for &(m, k, n, c0, c1) in &[(77, 64, 192, 64, 128), (130, 33, 50, 0, 50), (8, 256, 256, 16, 250), (1, 2, 3, 0, 3)] {
                let x: Vec<f32> = (0..m * k).map(|i| ((i * 37 % 101) as f32 - 50.0) / 50.0).collect();
                let w: Vec<f32> = (0..k * n).map(|i| ((i * 53 % 89) as f32 - 44.0) / 44.0).collect();
                let xm = Matrix::from_vec(m, k, x).expect("x");
                let wm = Matrix::from_vec(k, n, w.clone()).expect("w");
                let mut want = vec![1.0f32; m * (c1 - c0)];
                Ctx::default()
                    .gemm(&mut want, c1 - c0, xm.view(), false, wm.view().cols(c0, c1), false, 1.0, true, false)
                    .expect("fp32");
                let mut got = vec![1.0f32; m * (c1 - c0)];
                gemm_acc(&mut got, c1 - c0, xm.view(), &pack_weights(&w, k, n), k, n, c0, c1).expect("bf16");
                let worst = want.iter().zip(&got).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
                // Each product carries ~2·2^-9 relative error; sums of k terms of size ≤ 1.
                assert!(worst < 0.01 * (k as f32).sqrt(), "{m}×{k}×{n}: {worst}");
            }
            let x = Matrix::zeros(3, 4);
            assert!(gemm_acc(&mut [0.0; 12], 4, x.view(), &pack_weights(&[0.0; 16], 4, 4), 4, 4, 1, 4).is_err());
        }
    }
}
