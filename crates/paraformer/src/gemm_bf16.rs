//! The bf16 matrix product of the attention layers' Linear layers (`Precision::Bf16`):
//! `dst += x·W` with `x` and `W` rounded to bf16 and fp32 accumulation (`vdpbf16ps`),
//! on CPUs with AVX-512 BF16, or on AMX tiles where the CPU has them ([`crate::amx`]). `W` is
//! packed once per layer, in pairs of rows (`[in/2][out][2]`), the layout both read.

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


    /// Pairs of input rows per packed row group: the K step of an AMX tile (32 inputs).
    const K_PAIRS: usize = 16;

    /// `ceil(k/2)` rounded up to [`K_PAIRS`]: the packed weights' pair rows (zero beyond `k`).
    fn padded_pairs(k: usize) -> usize {
        k.div_ceil(2).div_ceil(K_PAIRS) * K_PAIRS
    }

    /// `wt` `[k, n]` row-major → `[k2p][n_pad][2]` bf16, `n_pad` = `n` rounded up to 16 and
    /// `k2p` = `ceil(k/2)` rounded up to 16 (zero padding).
    pub fn pack_weights(wt: &[f32], k: usize, n: usize) -> Vec<u16> {
        let np = n.div_ceil(16) * 16;
        let mut out = vec![0u16; padded_pairs(k) * np * 2];
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
        let (k2, k2p) = (k.div_ceil(2), padded_pairs(k));
        if x.cols != k || !c0.is_multiple_of(16) || c1 > n || c0 > c1 || wp.len() != k2p * np * 2 || !super::available() {
            return Err(internal(format!("bf16 gemm x {m}×{} with W {k}×{n} columns {c0}..{c1}", x.cols)));
        }
        if m == 0 || c0 == c1 {
            return Ok(());
        }
        if (m - 1) * dst_stride + (c1 - c0) > dst.len() || (m - 1) * x.stride + k > x.data.len() {
            return Err(internal(format!("bf16 gemm output {m}×{} (stride {dst_stride}) in {} values", c1 - c0, dst.len())));
        }
        let out = SharedMut(dst.as_mut_ptr());
        // AMX tiles take 32 rows at a time and K in steps of 16 pairs (the weights' padding).
        let amx = crate::amx::active();
        let (group, pairs) = if amx { (32, k2p) } else { (TILE, k2) };
        (0..m.div_ceil(BLOCK)).into_par_iter().for_each(|b| {
            let (r0, r1) = (b * BLOCK, ((b + 1) * BLOCK).min(m));
            // The block's rows as bf16 pairs (row stride `pairs`), padded with zero rows to
            // whole groups.
            let rows = (r1 - r0).div_ceil(group) * group;
            let mut a = vec![0u16; rows * pairs * 2];
            for r in r0..r1 {
                for (d, &v) in a[(r - r0) * pairs * 2..].iter_mut().zip(x.row(r)) {
                    *d = to_bf16(v);
                }
            }
            // SAFETY: AVX-512 BF16 (and AMX for `amx`) was checked above; block b alone writes
            // rows r0..r1 of `dst`, inside the bounds checked above.
            unsafe {
                if amx {
                    amx_block(&a, r1 - r0, k2p, wp, np, c0, c1, out.at(r0 * dst_stride), dst_stride)
                } else {
                    block(&a, r1 - r0, k2, wp, np, c0, c1, out.at(r0 * dst_stride), dst_stride)
                }
            };
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

    /// [`block`] on AMX tiles: 32 × 32 results at a time through a scratch tile, added to
    /// `dst` where they fall inside `rows` and `c0..c1`.
    #[allow(clippy::too_many_arguments)]
    unsafe fn amx_block(a: &[u16], rows: usize, k2p: usize, wp: &[u16], np: usize, c0: usize, c1: usize, dst: *mut f32, ld: usize) {
        let mut c = [[0.0f32; 32]; 32];
        for j0 in (c0..c1).step_by(32) {
            let cols = (c1 - j0).min(32);
            for t0 in (0..rows).step_by(32) {
                // SAFETY: `a` has whole groups of 32 rows; columns j0.. of `wp` up to j0 + 16
                // (or + 32 when more than 16 remain, which `np ≥ c1` covers).
                unsafe { crate::amx::gemm_32x32(a.as_ptr().add(t0 * k2p * 2), k2p, wp.as_ptr().add(j0 * 2), np, if cols > 16 { 32 } else { 16 }, &mut c) };
                for (r, cr) in c.iter().enumerate().take((rows - t0).min(32)) {
                    // SAFETY: row t0 + r < rows and columns j0 − c0 .. + cols of dst are in bounds.
                    let d = unsafe { std::slice::from_raw_parts_mut(dst.add((t0 + r) * ld + (j0 - c0)), cols) };
                    for (o, x) in d.iter_mut().zip(cr) {
                        *o += x;
                    }
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
            // Packed weights of the wrong size (here: without the padding to 16 pair rows).
            assert!(gemm_acc(&mut [0.0; 12], 4, x.view(), &[0u16; 2 * 16 * 2], 4, 4, 0, 4).is_err());
            assert!(gemm_acc(&mut [0.0; 12], 4, x.view(), &pack_weights(&[0.0; 16], 4, 4), 4, 4, 1, 4).is_err());
        }

        /// The AMX tiles against the AVX-512 BF16 kernel: the same bf16 operands, fp32 sums in
        /// another order. Shapes cover partial row groups (of 32), 16-column tails, inputs that
        /// are not a whole number of 32 (padded pair rows) and column ranges inside `n`.
        #[test]
        fn amx_gemm_matches_the_avx512_bf16_kernel() {
            if !crate::amx::supported() {
                eprintln!("skipped: no AMX-BF16 here (or the OS refused the tile state)");
                return;
            }
            let _switch = crate::amx::tests::SWITCH.lock().unwrap_or_else(|e| e.into_inner());
            for &(m, k, n, c0, c1) in &[(77, 64, 192, 64, 128), (130, 33, 50, 0, 50), (8, 256, 256, 16, 250), (1, 2, 3, 0, 3), (2048, 96, 288, 0, 288), (65, 192, 96, 32, 80)] {
                let x: Vec<f32> = (0..m * k).map(|i| ((i * 37 % 101) as f32 - 50.0) / 50.0).collect();
                let w: Vec<f32> = (0..k * n).map(|i| ((i * 53 % 89) as f32 - 44.0) / 44.0).collect();
                let xm = Matrix::from_vec(m, k, x).expect("x");
                let wp = pack_weights(&w, k, n);
                let run = |on: bool| {
                    crate::amx::set_enabled(on);
                    let mut out = vec![0.5f32; m * (c1 - c0)];
                    gemm_acc(&mut out, c1 - c0, xm.view(), &wp, k, n, c0, c1).expect("bf16");
                    out
                };
                let (plain, tiles) = (run(false), run(true));
                let worst = plain.iter().zip(&tiles).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
                assert!(worst < 1e-5 * k as f32, "{m}×{k}×{n} columns {c0}..{c1}: {worst}");
            }
        }
    }
}
