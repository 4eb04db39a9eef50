//! Intel AMX tile kernels for the bf16 products (`Precision::Bf16`): the two products of
//! the fused attention ([`crate::attention_fused`], SPEC §4–§5), i.e. the scores `q·kᵀ` of a
//! strip of 16 query rows and its value product `p·v`, and the attention layers' Linear
//! layers ([`crate::gemm_bf16`]).
//!
//! On CPUs with AMX-BF16 (Sapphire Rapids and later) one `tdpbf16ps` does 16 × 16 × 32
//! multiply-accumulates, several times what the same core does with `vdpbf16ps`, which it
//! issues at the rate of fp32 FMAs. The fused kernels already pack their operands in the
//! layouts the tiles read (queries row-major, keys in 16-column panels of bf16 pairs,
//! values as interleaved pairs of rows), so only the two products change; maxima,
//! exponentials and sums stay as they are. Accumulation is fp32, as with `vdpbf16ps`.
//!
//! Linux grants the 8 KiB tile state per process on request (`arch_prctl`), so the tiles
//! are used only where the CPU has them and that request succeeded; `PARAFORMER_AMX=0` or
//! [`set_enabled`] turns them off (the AVX-512 BF16 kernels then run). fp32 never uses them.

#[cfg(target_arch = "x86_64")]
use std::arch::asm;

#[cfg(target_arch = "x86_64")]
use crate::attention_fused::x86::{StripOut, MAX_D};
use std::sync::atomic::{AtomicU8, Ordering};

/// Whether the tile kernels may be used (set by [`set_enabled`], first read from
/// `PARAFORMER_AMX`).
static ENABLED: AtomicU8 = AtomicU8::new(u8::MAX);
/// Whether this CPU and OS run the tiles (probed once).
static SUPPORTED: AtomicU8 = AtomicU8::new(u8::MAX);

/// Whether the bf16 attention products run on AMX tiles in this process: the CPU has
/// AMX-TILE and AMX-BF16, the OS granted the tile state, and they are not turned off.
pub fn active() -> bool {
    enabled() && supported()
}

/// Turns the tile kernels on or off for the whole process (for side-by-side benchmarks;
/// off gives the AVX-512 BF16 kernels). Where the CPU lacks AMX, on stays off.
pub fn set_enabled(on: bool) {
    ENABLED.store(on as u8, Ordering::Relaxed);
}

/// The environment variable that turns the tiles off (`0`, `off`, `false`) or leaves them
/// on where supported (`1`, `on`, `true`; the default).
pub const ENV: &str = "PARAFORMER_AMX";

/// An error naming [`ENV`] when it holds anything but the values above (the kernels
/// themselves treat such a value as the default).
pub fn check_env() -> crate::Result<()> {
    match std::env::var_os(ENV) {
        None => Ok(()),
        Some(v) if ["0", "1", "on", "off", "true", "false"].iter().any(|ok| v == *ok) => Ok(()),
        Some(v) => Err(crate::Error::InvalidInput { argument: ENV.into(), reason: format!("{v:?}: expected 0, 1, on, off, true or false") }),
    }
}

fn enabled() -> bool {
    match ENABLED.load(Ordering::Relaxed) {
        u8::MAX => {
            let on = !matches!(std::env::var(ENV).as_deref(), Ok("0" | "off" | "false"));
            // A concurrent `set_enabled` wins over the environment.
            let _ = ENABLED.compare_exchange(u8::MAX, on as u8, Ordering::Relaxed, Ordering::Relaxed);
            ENABLED.load(Ordering::Relaxed) == 1
        }
        v => v == 1,
    }
}

/// Whether the CPU has the tiles and the OS lets this process use them.
pub fn supported() -> bool {
    match SUPPORTED.load(Ordering::Relaxed) {
        u8::MAX => {
            let s = probe();
            SUPPORTED.store(s as u8, Ordering::Relaxed);
            s
        }
        v => v == 1,
    }
}

#[cfg(all(target_arch = "x86_64", target_os = "linux"))]
fn probe() -> bool {
    use std::arch::x86_64::{__cpuid, __cpuid_count};
    // Leaf 7 EDX: bit 22 AMX-BF16, bit 24 AMX-TILE. The bf16 kernels around these
    // products also need AVX-512 BF16.
    #[allow(unused_unsafe)]
    // SAFETY: CPUID exists on every x86-64 CPU; leaf 7 is asked for only where leaf 0 lists it.
    let amx = unsafe { __cpuid(0).eax >= 7 && (__cpuid_count(7, 0).edx >> 22) & 0b101 == 0b101 };
    amx && crate::attention_fused::bf16_available() && request_tile_state()
}

#[cfg(not(all(target_arch = "x86_64", target_os = "linux")))]
fn probe() -> bool {
    false
}

/// Asks Linux for the tile data state (`arch_prctl(ARCH_REQ_XCOMP_PERM, XFEATURE_XTILEDATA)`,
/// kernels ≥ 5.16); without it the first tile instruction would fault.
#[cfg(all(target_arch = "x86_64", target_os = "linux"))]
fn request_tile_state() -> bool {
    const SYS_ARCH_PRCTL: usize = 158;
    const ARCH_REQ_XCOMP_PERM: usize = 0x1023;
    const XFEATURE_XTILEDATA: usize = 18;
    let ret: isize;
    // SAFETY: a plain system call that changes only this process's permitted XSAVE state.
    unsafe {
        asm!("syscall", inlateout("rax") SYS_ARCH_PRCTL as isize => ret, in("rdi") ARCH_REQ_XCOMP_PERM,
             in("rsi") XFEATURE_XTILEDATA, lateout("rcx") _, lateout("r11") _, options(nostack));
    }
    ret == 0
}

/// The 64-byte operand of `ldtilecfg` (palette 1): rows and bytes per row of tiles 0–7.
#[cfg(target_arch = "x86_64")]
#[repr(C, align(64))]
struct TileConfig([u8; 64]);

#[cfg(target_arch = "x86_64")]
impl TileConfig {
    fn new(tiles: [(u8, u16); 8]) -> Self {
        let mut c = [0u8; 64];
        c[0] = 1;
        for (t, (rows, colsb)) in tiles.into_iter().enumerate() {
            c[16 + 2 * t..18 + 2 * t].copy_from_slice(&colsb.to_le_bytes());
            c[48 + t] = rows;
        }
        Self(c)
    }

    /// Loads this configuration into the calling thread's tile state.
    ///
    /// # Safety
    /// [`active`] must have returned true in this process.
    unsafe fn load(&self) {
        // SAFETY: the caller checked AMX; the operand is 64 aligned bytes.
        unsafe { asm!("ldtilecfg [{}]", in(reg) self.0.as_ptr(), options(nostack, readonly)) };
    }
}

#[cfg(target_arch = "x86_64")]
impl TileConfig {
    /// [`TileConfig::load`], then tiles 4–7 (the accumulators of the kernels below) set to zero.
    ///
    /// # Safety
    /// As for [`TileConfig::load`]; tiles 4–7 must be configured.
    unsafe fn load_with_zero_accumulators(&self) {
        // SAFETY: per the caller.
        unsafe {
            self.load();
            asm!("tilezero tmm4", "tilezero tmm5", "tilezero tmm6", "tilezero tmm7", options(nostack, nomem));
        }
    }
}

/// Releases the tile state (so that context switches need not save it).
#[cfg(target_arch = "x86_64")]
unsafe fn release() {
    // SAFETY: only called after `TileConfig::load`.
    unsafe { asm!("tilerelease", options(nostack, nomem)) };
}

/// Scores of a strip: `s[r][j] = Σ_t q[r][t]·k[j][t]` for 16 rows and all `np` columns
/// (columns ≥ `n` set to −∞), from bf16 queries `[16][D]` and keys in 16-column panels
/// `[np/16][D/2][16][2]` (as [`crate::attention_fused`] packs them); `s` has row stride `ld`.
///
/// # Safety
/// [`active`]; `q` holds 16 rows of `D` values, `kp` `np/16` panels, `s` 16 rows of `ld ≥ np`
/// floats; `np` is a multiple of 32 and `D` is 16, 32, 64 or 96.
#[cfg(target_arch = "x86_64")]
pub(crate) unsafe fn scores<const D: usize>(q: *const u16, kp: *const u16, n: usize, np: usize, s: *mut f32, ld: usize) {
    const { assert!(D == 16 || D == 32 || D == 64 || D == 96) };
    // One K step covers 32 channels (64 bytes of a query row); D = 64 takes two, 96 three
    // (query tiles 0, 1 and 6).
    let kw = D.min(32);
    let (q_colsb, k_rows) = ((kw * 2) as u16, (kw / 2) as u8);
    let cfg = TileConfig::new([(16, q_colsb), (16, q_colsb), (k_rows, 64), (k_rows, 64), (16, 64), (16, 64), (16, 64), (16, 64)]);
    let (qs, ks, cs) = (D * 2, 64usize, ld * 4);
    // SAFETY: AMX per the caller; every tile access stays inside the buffers described above
    // (16 query rows, whole key panels, 16 strip rows of 16 floats at column p·16 < np).
    unsafe {
        cfg.load();
        asm!("tileloadd tmm0, [{q} + {qs}*1]", q = in(reg) q, qs = in(reg) qs, options(nostack, readonly));
        if D >= 64 {
            asm!("tileloadd tmm1, [{q} + {qs}*1]", q = in(reg) q.add(32), qs = in(reg) qs, options(nostack, readonly));
        }
        if D == 96 {
            asm!("tileloadd tmm6, [{q} + {qs}*1]", q = in(reg) q.add(64), qs = in(reg) qs, options(nostack, readonly));
        }
        let panel = 16 * D;
        // Two key panels against query tile $q (one K step of 32 channels), into tiles 4 and 5.
        macro_rules! k_step {
            ($q:literal, $k0:expr, $k1:expr) => {
                asm!(
                    "tileloadd tmm2, [{k0} + {ks}*1]",
                    "tileloadd tmm3, [{k1} + {ks}*1]",
                    concat!("tdpbf16ps tmm4, ", $q, ", tmm2"),
                    concat!("tdpbf16ps tmm5, ", $q, ", tmm3"),
                    k0 = in(reg) $k0, k1 = in(reg) $k1, ks = in(reg) ks, options(nostack, readonly),
                )
            };
        }
        for p in (0..np / 16).step_by(2) {
            let (k0, k1) = (kp.add(p * panel), kp.add((p + 1) * panel));
            asm!("tilezero tmm4", "tilezero tmm5", options(nostack, nomem));
            k_step!("tmm0", k0, k1);
            if D >= 64 {
                // Channels 32..64: pair rows 16..32 of each panel (16 rows × 32 values on).
                k_step!("tmm1", k0.add(512), k1.add(512));
            }
            if D == 96 {
                k_step!("tmm6", k0.add(1024), k1.add(1024));
            }
            asm!(
                "tilestored [{c0} + {cs}*1], tmm4",
                "tilestored [{c1} + {cs}*1], tmm5",
                c0 = in(reg) s.add(p * 16), c1 = in(reg) s.add(p * 16 + 16), cs = in(reg) cs, options(nostack),
            );
        }
        release();
        // Padding keys (zeros in the panels) must not take probability.
        for r in 0..16 {
            for j in n..np {
                *s.add(r * ld + j) = f32::NEG_INFINITY;
            }
        }
    }
}

/// `out[r][..D] = Σ_j p[r][j]·v[j][..D]` for 16 rows, from bf16 probabilities `p16`
/// (`[16][ld]`) and values as pairs of rows `[np/2][D][2]` (zero beyond `n`).
///
/// # Safety
/// [`active`]; `p16` holds 16 rows of `ld` values whose columns `n..` up to the next
/// multiple of 32 are zero (and within `ld`); `v16` holds `n` rounded up to 32 rows;
/// `D` is 16, 32, 64 or 96.
#[cfg(target_arch = "x86_64")]
pub(crate) unsafe fn values<const D: usize>(p16: *const u16, ld: usize, n: usize, v16: *const u16, out: &mut StripOut) {
    const { assert!(D == 16 || D == 32 || D == 64 || D == 96) };
    if D == 96 {
        // SAFETY: as for this function.
        return unsafe { values_96(p16, ld, n, v16, out) };
    }
    let cfg = TileConfig::new([(16, 64); 8]);
    let (ps, vs, os) = (ld * 2, D * 4, MAX_D * 4);
    let o = out.as_mut_ptr() as *mut f32;
    // SAFETY: AMX per the caller; blocks of 32 keys read 16 rows × 64 bytes of `p16` at column
    // j0 < ld and 16 pairs × 16 columns of `v16` below n rounded up to 32; the results are
    // 16 × D floats of `out`.
    unsafe {
        cfg.load_with_zero_accumulators();
        for j0 in (0..n.div_ceil(32) * 32).step_by(32) {
            let (a, b) = (p16.add(j0), v16.add(j0 * D));
            match D {
                16 => asm!(
                    "tileloadd tmm0, [{a} + {ps}*1]",
                    "tileloadd tmm1, [{b} + {vs}*1]",
                    "tdpbf16ps tmm4, tmm0, tmm1",
                    a = in(reg) a, b = in(reg) b, ps = in(reg) ps, vs = in(reg) vs, options(nostack, readonly),
                ),
                32 => asm!(
                    "tileloadd tmm0, [{a} + {ps}*1]",
                    "tileloadd tmm1, [{b} + {vs}*1]",
                    "tileloadd tmm2, [{b1} + {vs}*1]",
                    "tdpbf16ps tmm4, tmm0, tmm1",
                    "tdpbf16ps tmm5, tmm0, tmm2",
                    a = in(reg) a, b = in(reg) b, b1 = in(reg) b.add(32), ps = in(reg) ps, vs = in(reg) vs,
                    options(nostack, readonly),
                ),
                _ => asm!(
                    "tileloadd tmm0, [{a} + {ps}*1]",
                    "tileloadd tmm1, [{b} + {vs}*1]",
                    "tileloadd tmm2, [{b1} + {vs}*1]",
                    "tileloadd tmm3, [{b2} + {vs}*1]",
                    "tdpbf16ps tmm4, tmm0, tmm1",
                    "tdpbf16ps tmm5, tmm0, tmm2",
                    "tdpbf16ps tmm6, tmm0, tmm3",
                    "tileloadd tmm1, [{b3} + {vs}*1]",
                    "tdpbf16ps tmm7, tmm0, tmm1",
                    a = in(reg) a, b = in(reg) b, b1 = in(reg) b.add(32), b2 = in(reg) b.add(64), b3 = in(reg) b.add(96),
                    ps = in(reg) ps, vs = in(reg) vs, options(nostack, readonly),
                ),
            }
        }
        asm!("tilestored [{o} + {os}*1], tmm4", o = in(reg) o, os = in(reg) os, options(nostack));
        if D >= 32 {
            asm!("tilestored [{o} + {os}*1], tmm5", o = in(reg) o.add(16), os = in(reg) os, options(nostack));
        }
        if D == 64 {
            asm!(
                "tilestored [{o2} + {os}*1], tmm6",
                "tilestored [{o3} + {os}*1], tmm7",
                o2 = in(reg) o.add(32), o3 = in(reg) o.add(48), os = in(reg) os, options(nostack),
            );
        }
        release();
    }
}

/// [`values`] at head width 96: six accumulator tiles (2–7) of 16 columns, one value tile
/// (1) loaded in turn.
#[cfg(target_arch = "x86_64")]
unsafe fn values_96(p16: *const u16, ld: usize, n: usize, v16: *const u16, out: &mut StripOut) {
    const D: usize = 96;
    let cfg = TileConfig::new([(16, 64); 8]);
    let (ps, vs, os) = (ld * 2, D * 4, MAX_D * 4);
    let o = out.as_mut_ptr() as *mut f32;
    // SAFETY: as for `values`; value tile c reads columns 16c..16c+16 of 16 pair rows.
    unsafe {
        cfg.load_with_zero_accumulators();
        asm!("tilezero tmm2", "tilezero tmm3", options(nostack, nomem));
        // Value columns 16c..16c+16 into accumulator tile $acc.
        macro_rules! column_block {
            ($acc:literal, $b:expr) => {
                asm!(
                    "tileloadd tmm1, [{b} + {vs}*1]",
                    concat!("tdpbf16ps ", $acc, ", tmm0, tmm1"),
                    b = in(reg) $b, vs = in(reg) vs, options(nostack, readonly),
                )
            };
        }
        for j0 in (0..n.div_ceil(32) * 32).step_by(32) {
            let b = v16.add(j0 * D);
            asm!("tileloadd tmm0, [{a} + {ps}*1]", a = in(reg) p16.add(j0), ps = in(reg) ps, options(nostack, readonly));
            column_block!("tmm2", b);
            column_block!("tmm3", b.add(32));
            column_block!("tmm4", b.add(64));
            column_block!("tmm5", b.add(96));
            column_block!("tmm6", b.add(128));
            column_block!("tmm7", b.add(160));
        }
        asm!(
            "tilestored [{o0} + {os}*1], tmm2",
            "tilestored [{o1} + {os}*1], tmm3",
            "tilestored [{o2} + {os}*1], tmm4",
            "tilestored [{o3} + {os}*1], tmm5",
            "tilestored [{o4} + {os}*1], tmm6",
            "tilestored [{o5} + {os}*1], tmm7",
            o0 = in(reg) o, o1 = in(reg) o.add(16), o2 = in(reg) o.add(32), o3 = in(reg) o.add(48),
            o4 = in(reg) o.add(64), o5 = in(reg) o.add(80), os = in(reg) os, options(nostack),
        );
        release();
    }
}

/// `C = A·W` for 32 rows and 32 columns: `a` holds 32 rows of `k2p` bf16 pairs (row stride
/// `k2p` pairs, `k2p` a multiple of 16), `w` the packed weights from column `j0` on
/// (`[k2p][np][2]`, row stride `np` pairs); `cols` is 16 or 32. `c` gets `[32][32]` floats.
///
/// # Safety
/// [`active`]; the buffers hold what is described (for `cols` = 16, only 16 columns of `w`
/// are read).
#[cfg(target_arch = "x86_64")]
pub(crate) unsafe fn gemm_32x32(a: *const u16, k2p: usize, w: *const u16, np: usize, cols: usize, c: &mut [[f32; 32]; 32]) {
    let cfg = TileConfig::new([(16, 64); 8]);
    let (as_, ws, cs) = (k2p * 4, np * 4, 32usize * 4);
    let o = c.as_mut_ptr() as *mut f32;
    // SAFETY: AMX per the caller; K blocks of 16 pairs read 16 rows of `a` (64 bytes each, two
    // row groups) and 16 pair rows of `w` (64 bytes at column j0 and, for 32 columns, j0 + 16).
    unsafe {
        cfg.load_with_zero_accumulators();
        for kb in (0..k2p).step_by(16) {
            let (a0, a1, b0) = (a.add(kb * 2), a.add((16 * k2p + kb) * 2), w.add(kb * np * 2));
            if cols == 32 {
                asm!(
                    "tileloadd tmm0, [{a0} + {as_}*1]",
                    "tileloadd tmm2, [{b0} + {ws}*1]",
                    "tileloadd tmm3, [{b1} + {ws}*1]",
                    "tdpbf16ps tmm4, tmm0, tmm2",
                    "tdpbf16ps tmm5, tmm0, tmm3",
                    "tileloadd tmm1, [{a1} + {as_}*1]",
                    "tdpbf16ps tmm6, tmm1, tmm2",
                    "tdpbf16ps tmm7, tmm1, tmm3",
                    a0 = in(reg) a0, a1 = in(reg) a1, b0 = in(reg) b0, b1 = in(reg) b0.add(32),
                    as_ = in(reg) as_, ws = in(reg) ws, options(nostack, readonly),
                );
            } else {
                asm!(
                    "tileloadd tmm0, [{a0} + {as_}*1]",
                    "tileloadd tmm2, [{b0} + {ws}*1]",
                    "tdpbf16ps tmm4, tmm0, tmm2",
                    "tileloadd tmm1, [{a1} + {as_}*1]",
                    "tdpbf16ps tmm6, tmm1, tmm2",
                    a0 = in(reg) a0, a1 = in(reg) a1, b0 = in(reg) b0, as_ = in(reg) as_, ws = in(reg) ws,
                    options(nostack, readonly),
                );
            }
        }
        asm!(
            "tilestored [{o0} + {cs}*1], tmm4",
            "tilestored [{o1} + {cs}*1], tmm5",
            "tilestored [{o2} + {cs}*1], tmm6",
            "tilestored [{o3} + {cs}*1], tmm7",
            o0 = in(reg) o, o1 = in(reg) o.add(16), o2 = in(reg) o.add(16 * 32), o3 = in(reg) o.add(16 * 32 + 16),
            cs = in(reg) cs, options(nostack),
        );
        release();
    }
}

#[cfg(all(test, target_arch = "x86_64"))]
pub(crate) mod tests {
    use crate::attention::{attention, cross_attention_shared};
    use crate::attention_fused::tests::{general, max_diff, random};
    use crate::kernels::{Ctx, Precision};

    /// Held by the tests that switch the tiles off and on (a process-wide switch), so that
    /// each compares the two paths it means to.
    pub(crate) static SWITCH: std::sync::Mutex<()> = std::sync::Mutex::new(());

    fn mean_diff(a: &[f32], b: &[f32]) -> f32 {
        a.iter().zip(b).map(|(x, y)| (x - y).abs()).sum::<f32>() / a.len().max(1) as f32
    }

    /// The tile kernels against the fp32 general path and beside the AVX-512 BF16 kernels:
    /// the same bf16 operands with fp32 accumulation in another order, so both are as far
    /// from fp32 (a score that moves by an fp32 rounding can round a probability to the
    /// neighbouring bf16, 0.4% of its value). With tiles the shared cross attention's column
    /// direction is a second row pass over `Sᵀ` (see `cross_attention_shared`), with its own
    /// roundings. Sizes cover every head width, partial strips and partial blocks of 32 keys.
    #[test]
    fn tiles_match_the_avx512_bf16_kernels() {
        if !super::supported() {
            eprintln!("skipped: no AMX-BF16 here (or the OS refused the tile state)");
            return;
        }
        let _switch = SWITCH.lock().unwrap_or_else(|e| e.into_inner());
        let bf = Ctx::with_precision(Precision::Bf16);
        let amp = 2.0;
        for &(m, n, c, heads) in &[(77, 53, 64, 4), (600, 301, 64, 2), (33, 517, 128, 2), (5, 1, 32, 2), (300, 300, 64, 1), (2048, 2048, 96, 3), (17, 64, 192, 3), (77, 53, 96, 1), (300, 517, 192, 2)] {
            let (q, k, v) = (random(m, c, 11, amp), random(n, c, 12, amp), random(n, c, 13, 1.0));
            let vx = random(m, c, 14, 1.0);
            let (want, _) = attention(&general(), q.view(), k.view(), v.view(), heads, false).expect("fp32");
            let (wx, wy) = cross_attention_shared(&general(), q.view(), k.view(), vx.view(), v.view(), heads).expect("fp32");
            let run = |amx: bool| {
                super::set_enabled(amx);
                let (a, _) = attention(&bf, q.view(), k.view(), v.view(), heads, false).expect("self");
                let (x, y) = cross_attention_shared(&bf, q.view(), k.view(), vx.view(), v.view(), heads).expect("cross");
                [a.data, x.data, y.data]
            };
            let (plain, tiles) = (run(false), run(true));
            assert!(super::active(), "turned back on");
            for (i, (name, w)) in [("self", &want.data), ("cross x", &wx.data), ("cross y", &wy.data)].into_iter().enumerate() {
                let (ep, et) = (max_diff(w, &plain[i]), max_diff(w, &tiles[i]));
                let (mp, mt) = (mean_diff(w, &plain[i]), mean_diff(w, &tiles[i]));
                eprintln!("{name} {m}×{n} c{c} h{heads}: from fp32, max/mean tiles {et:.2e}/{mt:.2e}, avx-512 bf16 {ep:.2e}/{mp:.2e}");
                // The bound of the AVX-512 BF16 kernels' own test, and no larger typical error.
                assert!(et < 0.005 * amp && mt < 1.5 * mp + 2e-4, "{name} {m}×{n} c{c} h{heads}: tiles {et}/{mt}, avx-512 bf16 {ep}/{mp}");
            }
        }
    }
}
