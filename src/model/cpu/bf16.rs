//! Matrix products in bfloat16, accumulating in f32: on Intel AMX tiles where the CPU has
//! them, else with AVX-512 BF16 dot products.
//!
//! Why: the network's gemms (the backbone's pointwise layers, the upsampler's 3x3 convolutions as
//! im2col) are most of its f32 time. One AMX `tdpbf16ps` does 16x16x32 multiply-adds; one
//! AVX-512 BF16 `vdpbf16ps` does twice the multiply-adds of an f32 FMA (AMD Zen 4 and later,
//! Intel Cooper Lake and Sapphire Rapids and later; measured on a Zen 4 core: 225 GFLOP/s
//! against 108 for the f32 gemm, `cargo bench --bench network`). Either way the network becomes
//! bound by its memory-bound stages instead. The price is bf16 rounding of both operands (8
//! significant bits); products and sums stay f32. Used only when the caller chose
//! [`crate::model::Precision::Bf16`]; f32 remains the exact path (parity). Both kernels read the same
//! packed weights and compute the same function up to the order of the f32 sums.
//!
//! The tile instructions are written as inline assembly: Rust's AMX intrinsics are unstable.

#[cfg(target_arch = "x86_64")]
use std::arch::asm;
use std::fmt;
use std::sync::OnceLock;

/// Rows and columns (f32) of one accumulator tile.
const TILE_ROWS: usize = 16;
const TILE_COLUMNS: usize = 16;
/// bf16 values of k per tile step (one 64-byte tile row).
const TILE_K: usize = 32;
/// Rows of the left-hand side per tile pass (two accumulator tiles high).
const BLOCK_ROWS: usize = 2 * TILE_ROWS;

/// The instructions that run this process's bf16 products.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Bf16Instructions {
    /// Intel AMX tiles (`tdpbf16ps`).
    AmxTiles,
    /// AVX-512 BF16 dot products (`vdpbf16ps`).
    Avx512Dot,
}

impl fmt::Display for Bf16Instructions {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::AmxTiles => "AMX tiles",
            Self::Avx512Dot => "AVX-512 BF16",
        })
    }
}

/// The fastest bf16 instructions this process may use, `None` where the CPU has neither. Asked once
/// per process.
pub fn instructions() -> Option<Bf16Instructions> {
    static INSTRUCTIONS: OnceLock<Option<Bf16Instructions>> = OnceLock::new();
    *INSTRUCTIONS.get_or_init(|| {
        if tiles_available() {
            Some(Bf16Instructions::AmxTiles)
        } else if dot_available() {
            Some(Bf16Instructions::Avx512Dot)
        } else {
            None
        }
    })
}

/// Whether bf16 products can run here at all.
pub fn available() -> bool {
    instructions().is_some()
}

/// Whether the CPU has AVX-512F and AVX-512 BF16.
fn dot_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bf16")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Whether this process may use AMX bf16 tiles: the CPU has them (CPUID) and Linux granted
/// the tile data state (`arch_prctl(ARCH_REQ_XCOMP_PERM)`, Linux 5.16+). Asked once per process.
fn tiles_available() -> bool {
    static AVAILABLE: OnceLock<bool> = OnceLock::new();
    *AVAILABLE.get_or_init(request_tiles)
}

#[cfg(all(target_arch = "x86_64", target_os = "linux"))]
fn request_tiles() -> bool {
    // CPUID leaf 7 exists on every x86_64 CPU that runs this binary.
    let leaf7 = std::arch::x86_64::__cpuid_count(7, 0);
    let amx_bf16 = leaf7.edx & (1 << 22) != 0;
    let amx_tile = leaf7.edx & (1 << 24) != 0;
    if !(amx_bf16 && amx_tile) {
        return false;
    }
    const ARCH_REQ_XCOMP_PERM: libc::c_long = 0x1023;
    const XFEATURE_XTILEDATA: libc::c_long = 18;
    // SAFETY: a system call with integer arguments; Linux answers 0 when it grants this
    // process the tile data state, an error otherwise.
    let granted = unsafe {
        libc::syscall(
            libc::SYS_arch_prctl,
            ARCH_REQ_XCOMP_PERM,
            XFEATURE_XTILEDATA,
        )
    };
    granted == 0
}

#[cfg(not(all(target_arch = "x86_64", target_os = "linux")))]
fn request_tiles() -> bool {
    false
}

/// Rounds to the nearest bf16, ties to even; NaN stays NaN.
#[inline]
pub fn to_bf16(value: f32) -> u16 {
    let bits = value.to_bits();
    if value.is_nan() {
        return ((bits >> 16) | 0x40) as u16;
    }
    ((bits + 0x7fff + ((bits >> 16) & 1)) >> 16) as u16
}

#[cfg(test)]
fn from_bf16(value: u16) -> f32 {
    f32::from_bits((value as u32) << 16)
}

/// Rounds `values` into `out` (same length), 16 at a time with AVX-512 BF16 where the CPU has
/// it (every CPU with AMX does).
pub fn round_into(values: &[f32], out: &mut [u16]) {
    assert_eq!(
        values.len(),
        out.len(),
        "round_into: lengths differ; this is a bug"
    );
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx512bf16") {
        // SAFETY: the CPU has AVX-512 BF16 (checked just above).
        done = unsafe { round_into_avx512(values, out) };
    }
    for (o, v) in out[done..].iter_mut().zip(&values[done..]) {
        *o = to_bf16(*v);
    }
}

/// Rounds the leading multiple of 16 values; returns how many.
///
/// # Safety
/// The CPU must have AVX-512F and AVX-512 BF16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn round_into_avx512(values: &[f32], out: &mut [u16]) -> usize {
    use std::arch::x86_64::{__m256i, _mm256_storeu_si256, _mm512_cvtneps_pbh, _mm512_loadu_ps};
    let whole = values.len().min(out.len()) / 16 * 16;
    for start in (0..whole).step_by(16) {
        // SAFETY: 16 values from `start` lie inside both slices (start + 16 <= whole).
        unsafe {
            let rounded = _mm512_cvtneps_pbh(_mm512_loadu_ps(values.as_ptr().add(start)));
            let bits: __m256i = std::mem::transmute(rounded);
            _mm256_storeu_si256(out.as_mut_ptr().add(start).cast(), bits);
        }
    }
    whole
}

/// Rows a left-hand side of `m` rows must hold: the tile routine reads whole 32-row blocks (rows past
/// `m` are read and their results discarded).
pub fn padded_rows(m: usize) -> usize {
    m.div_ceil(BLOCK_ROWS) * BLOCK_ROWS
}

/// A layer's weights `[k, n]` and bias `[n]` laid out for the tiles: for each 16-column block
/// and each 32-deep step of k, one 1 KiB tile of 16 rows (pairs of k) x 16 columns x 2 bf16;
/// the bias as one 16-float row per column block (accumulators start from it).
pub struct Bf16Weights {
    n: usize,
    k_steps: usize,
    column_blocks: usize,
    tiles: Vec<u16>,
    bias_rows: Vec<[f32; TILE_COLUMNS]>,
}

impl Bf16Weights {
    /// From a row-major `[k, n]` f32 matrix and its bias.
    pub fn new(matrix: &[f32], k: usize, n: usize, bias: &[f32]) -> Self {
        assert_eq!(matrix.len(), k * n, "matrix is not [k, n]; this is a bug");
        assert_eq!(bias.len(), n, "bias is not [n]; this is a bug");
        let k_steps = k.div_ceil(TILE_K);
        let column_blocks = n.div_ceil(TILE_COLUMNS);
        let tile_len = TILE_ROWS * TILE_COLUMNS * 2;
        let mut tiles = vec![0u16; column_blocks * k_steps * tile_len];
        for (index, tile) in tiles.chunks_exact_mut(tile_len).enumerate() {
            let (block, step) = (index / k_steps, index % k_steps);
            for (position, value) in tile.iter_mut().enumerate() {
                let (pair, column, half) = (position / 32, position % 32 / 2, position % 2);
                let row = step * TILE_K + 2 * pair + half;
                let col = block * TILE_COLUMNS + column;
                if row < k && col < n {
                    *value = to_bf16(matrix[row * n + col]);
                }
            }
        }
        let bias_rows = (0..column_blocks)
            .map(|block| {
                let mut row = [0f32; TILE_COLUMNS];
                for (c, r) in row.iter_mut().enumerate() {
                    *r = bias.get(block * TILE_COLUMNS + c).copied().unwrap_or(0.0);
                }
                row
            })
            .collect();
        Self {
            n,
            k_steps,
            column_blocks,
            tiles,
            bias_rows,
        }
    }

    /// Row length of the left-hand side these weights multiply: k padded to whole tile steps
    /// (the padding must hold zeros).
    pub fn lhs_stride(&self) -> usize {
        self.k_steps * TILE_K
    }

    fn tile(&self, block: usize, step: usize) -> *const u16 {
        self.tiles[(block * self.k_steps + step) * TILE_ROWS * TILE_COLUMNS * 2..].as_ptr()
    }
}

/// Tile configuration: palette 1, eight tiles of 16 rows x 64 bytes.
#[repr(C, align(64))]
struct TileConfig([u8; 64]);

impl TileConfig {
    fn all_full() -> Self {
        let mut bytes = [0u8; 64];
        bytes[0] = 1;
        for tile in 0..8 {
            bytes[16 + 2 * tile] = 64; // bytes per row, little-endian u16
            bytes[48 + tile] = TILE_ROWS as u8;
        }
        Self(bytes)
    }
}

/// `out[i, j] = bias[j] + sum_k lhs[i, k] * weights[k, j]` for `i < m`, on this thread, with
/// this process's [`kernel`].
///
/// `lhs`: `[padded_rows(m), weights.lhs_stride()]` bf16, row-major, zeros past `k` in each row.
/// `out`: `[m, weights.n()]`, row-major.
pub fn multiply(lhs: &[u16], m: usize, weights: &Bf16Weights, out: &mut [f32]) {
    assert!(
        lhs.len() >= padded_rows(m) * weights.lhs_stride() && out.len() >= m * weights.n,
        "lhs or out too short; this is a bug"
    );
    match instructions() {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: the tiles are available and permitted, and the sizes were checked.
        Some(Bf16Instructions::AmxTiles) => unsafe { multiply_tiles(lhs, m, weights, out) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: the CPU has AVX-512F and AVX-512 BF16, and the sizes were checked.
        Some(Bf16Instructions::Avx512Dot) => unsafe { multiply_dot(lhs, m, weights, out) },
        _ => panic!("no bf16 instructions on this CPU; this is a bug (callers check first)"),
    }
}

/// The kernel: per 32-row block, two accumulator tiles per 16-column block, two column blocks
/// at a time (tmm0-3 accumulators, tmm4-5 lhs, tmm6-7 weights).
///
/// # Safety
/// AMX must be available and granted; `lhs` and `out` as [`multiply`] asserts.
#[cfg(target_arch = "x86_64")]
unsafe fn multiply_tiles(lhs: &[u16], m: usize, weights: &Bf16Weights, out: &mut [f32]) {
    let (stride, n) = (weights.lhs_stride(), weights.n);
    let config = TileConfig::all_full();
    let mut scratch = [[0f32; TILE_ROWS * TILE_COLUMNS]; 2];
    let last_block = weights.column_blocks - 1;
    // SAFETY (every block below): tile loads read 16 rows of 64 bytes inside `lhs` (rows below
    // padded_rows(m), columns below its stride), inside one packed 1 KiB weight tile, or one
    // 64-byte bias row (stride 0); stores write whole tiles inside `out` (when all 32 rows and
    // 16 columns exist) or the scratch tiles. Tile registers are volatile and nothing else in
    // this process uses them while this thread runs the tile routine.
    unsafe {
        asm!("ldtilecfg [{}]", in(reg) config.0.as_ptr(), options(nostack, readonly));
        for row_block in (0..m).step_by(BLOCK_ROWS) {
            let a0 = lhs.as_ptr().add(row_block * stride);
            let a1 = a0.add(TILE_ROWS * stride);
            let full_rows = row_block + BLOCK_ROWS <= m;
            let mut block = 0;
            while block <= last_block {
                let pair = block < last_block;
                asm!(
                    "tileloadd tmm0, [{b0} + {zero}*1]",
                    "tileloadd tmm1, [{b0} + {zero}*1]",
                    "tileloadd tmm2, [{b1} + {zero}*1]",
                    "tileloadd tmm3, [{b1} + {zero}*1]",
                    b0 = in(reg) weights.bias_rows[block].as_ptr(),
                    b1 = in(reg) weights.bias_rows[(block + 1).min(last_block)].as_ptr(),
                    zero = in(reg) 0usize,
                    options(nostack, readonly),
                );
                for step in 0..weights.k_steps {
                    let k0 = step * TILE_K;
                    asm!(
                        "tileloadd tmm4, [{a0} + {s}*1]",
                        "tileloadd tmm5, [{a1} + {s}*1]",
                        "tileloadd tmm6, [{w0} + {t}*1]",
                        "tdpbf16ps tmm0, tmm4, tmm6",
                        "tdpbf16ps tmm1, tmm5, tmm6",
                        a0 = in(reg) a0.add(k0),
                        a1 = in(reg) a1.add(k0),
                        w0 = in(reg) weights.tile(block, step),
                        s = in(reg) stride * 2,
                        t = in(reg) 64usize,
                        options(nostack, readonly),
                    );
                    if pair {
                        asm!(
                            "tileloadd tmm7, [{w1} + {t}*1]",
                            "tdpbf16ps tmm2, tmm4, tmm7",
                            "tdpbf16ps tmm3, tmm5, tmm7",
                            w1 = in(reg) weights.tile(block + 1, step),
                            t = in(reg) 64usize,
                            options(nostack, readonly),
                        );
                    }
                }
                let blocks_done = if pair { 2 } else { 1 };
                for b in 0..blocks_done {
                    let col0 = (block + b) * TILE_COLUMNS;
                    let cols = (n - col0).min(TILE_COLUMNS);
                    let direct = full_rows && cols == TILE_COLUMNS;
                    let (c0, c1, row_bytes) = if direct {
                        let c0 = out.as_mut_ptr().add(row_block * n + col0);
                        (c0, c0.add(TILE_ROWS * n), n * 4)
                    } else {
                        let [s0, s1] = &mut scratch;
                        (s0.as_mut_ptr(), s1.as_mut_ptr(), TILE_COLUMNS * 4)
                    };
                    if b == 0 {
                        asm!(
                            "tilestored [{c0} + {t}*1], tmm0",
                            "tilestored [{c1} + {t}*1], tmm1",
                            c0 = in(reg) c0, c1 = in(reg) c1, t = in(reg) row_bytes,
                            options(nostack),
                        );
                    } else {
                        asm!(
                            "tilestored [{c0} + {t}*1], tmm2",
                            "tilestored [{c1} + {t}*1], tmm3",
                            c0 = in(reg) c0, c1 = in(reg) c1, t = in(reg) row_bytes,
                            options(nostack),
                        );
                    }
                    if direct {
                        continue;
                    }
                    for (half, tile) in scratch.iter().enumerate() {
                        for r in 0..TILE_ROWS {
                            let row = row_block + half * TILE_ROWS + r;
                            if row >= m {
                                break;
                            }
                            out[row * n + col0..row * n + col0 + cols]
                                .copy_from_slice(&tile[r * TILE_COLUMNS..r * TILE_COLUMNS + cols]);
                        }
                    }
                }
                block += blocks_done;
            }
        }
        asm!("tilerelease", options(nostack, nomem));
    }
}

/// Rows of the left-hand side per pass of the AVX-512 BF16 routine.
const DOT_ROWS: usize = 8;

/// `multiply` with AVX-512 BF16 dot products (`vdpbf16ps`: per f32 lane, a pair of bf16
/// products added to the accumulator) instead of tiles, on the same packed weights: each
/// 64-byte row of a weight tile is one register of 16 columns x (pair of k). Eight rows x up to
/// three column blocks of accumulators (24 registers) per pass.
///
/// # Safety
/// The CPU must have AVX-512F and AVX-512 BF16; `lhs` and `out` as [`multiply`] asserts.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn multiply_dot(lhs: &[u16], m: usize, weights: &Bf16Weights, out: &mut [f32]) {
    let mut block = 0;
    while block < weights.column_blocks {
        let group = (weights.column_blocks - block).min(3);
        for row0 in (0..m).step_by(DOT_ROWS) {
            let rows = (m - row0).min(DOT_ROWS);
            // SAFETY: DOT_ROWS rows from row0 lie inside `lhs` (it holds padded_rows(m), a
            // multiple of 32, which DOT_ROWS divides); `rows` rows of `out` from row0 exist.
            unsafe {
                let a = lhs.as_ptr().add(row0 * weights.lhs_stride());
                let c = out.as_mut_ptr().add(row0 * weights.n);
                match group {
                    3 => dot_pass::<3>(a, weights, block, rows, c),
                    2 => dot_pass::<2>(a, weights, block, rows, c),
                    _ => dot_pass::<1>(a, weights, block, rows, c),
                }
            }
        }
        block += group;
    }
}

/// One pass of [`multiply_dot`]: `NB` column blocks from `block`, the DOT_ROWS rows at `a`
/// (their first `rows` stored at `c`, row stride `weights.n`).
///
/// # Safety
/// As [`multiply_dot`]; `a` points at DOT_ROWS readable rows of `weights.lhs_stride()` bf16,
/// `c` at `rows` writable rows of `weights.n` f32.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
#[inline]
unsafe fn dot_pass<const NB: usize>(
    a: *const u16,
    weights: &Bf16Weights,
    block: usize,
    rows: usize,
    c: *mut f32,
) {
    use std::arch::x86_64::{
        __m512, __m512bh, _mm512_dpbf16_ps, _mm512_loadu_ps, _mm512_loadu_si512,
        _mm512_mask_storeu_ps, _mm512_set1_epi32,
    };
    let stride = weights.lhs_stride();
    let tile_len = TILE_ROWS * TILE_COLUMNS * 2;
    // SAFETY: every pointer below stays inside the packed tiles of blocks block..block+NB,
    // the DOT_ROWS rows at `a`, the bias rows, or the `rows` output rows (see the caller).
    unsafe {
        let mut acc: [[__m512; NB]; DOT_ROWS] =
            [[_mm512_loadu_ps(weights.bias_rows[block].as_ptr()); NB]; DOT_ROWS];
        for b in 1..NB {
            let bias = _mm512_loadu_ps(weights.bias_rows[block + b].as_ptr());
            for row in acc.iter_mut() {
                row[b] = bias;
            }
        }
        let tiles = weights.tiles.as_ptr();
        for step in 0..weights.k_steps {
            let tile: [*const u16; NB] = std::array::from_fn(|b| {
                tiles.add(((block + b) * weights.k_steps + step) * tile_len)
            });
            let a_step = a.add(step * TILE_K);
            for pair in 0..TILE_ROWS {
                let w: [__m512bh; NB] = std::array::from_fn(|b| {
                    std::mem::transmute(_mm512_loadu_si512(tile[b].add(pair * 32).cast()))
                });
                for (i, row) in acc.iter_mut().enumerate() {
                    let x: __m512bh = std::mem::transmute(_mm512_set1_epi32(
                        a_step
                            .add(i * stride + 2 * pair)
                            .cast::<i32>()
                            .read_unaligned(),
                    ));
                    for b in 0..NB {
                        row[b] = _mm512_dpbf16_ps(row[b], x, w[b]);
                    }
                }
            }
        }
        for (i, row) in acc.iter().enumerate().take(rows) {
            for (b, value) in row.iter().enumerate() {
                let col0 = (block + b) * TILE_COLUMNS;
                let cols = (weights.n - col0).min(TILE_COLUMNS);
                let mask = if cols == TILE_COLUMNS {
                    u16::MAX
                } else {
                    (1u16 << cols) - 1
                };
                _mm512_mask_storeu_ps(c.add(i * weights.n + col0), mask, *value);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounding_to_bf16_is_to_nearest_even() {
        assert_eq!(to_bf16(1.0), 0x3f80);
        assert_eq!(from_bf16(to_bf16(-3.0)), -3.0);
        // Halfway between 1 and the next bf16 (1 + 2^-7): ties go to the even one, 1.
        assert_eq!(from_bf16(to_bf16(1.0 + 1.0 / 256.0)), 1.0);
        assert_eq!(from_bf16(to_bf16(1.0 + 3.0 / 256.0)), 1.0 + 4.0 / 256.0);
        assert!(from_bf16(to_bf16(f32::NAN)).is_nan());
    }

    type Product = unsafe fn(&[u16], usize, &Bf16Weights, &mut [f32]);

    /// `product` equals an f64 product of the bf16-rounded operands, for shapes with every kind
    /// of edge: rows not a multiple of 8 or 32, k not a multiple of 32, n of 12 / 20 / 48 / 80 /
    /// 96 (one, an odd number of, and groups of column blocks, partial last blocks).
    fn assert_equals_the_rounded_operands_product(product: Product) {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut random = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5
        };
        for (m, k, n) in [
            (37, 50, 12),
            (100, 216, 48),
            (64, 96, 96),
            (5, 384, 20),
            (9, 40, 80),
        ] {
            let input: Vec<f32> = (0..m * k).map(|_| random()).collect();
            let matrix: Vec<f32> = (0..k * n).map(|_| random()).collect();
            let bias: Vec<f32> = (0..n).map(|_| random()).collect();
            let weights = Bf16Weights::new(&matrix, k, n, &bias);
            let mut out = vec![f32::NAN; m * n];
            let stride = weights.lhs_stride();
            let mut lhs = vec![0u16; padded_rows(m) * stride];
            for (row, values) in lhs.chunks_exact_mut(stride).zip(input.chunks_exact(k)) {
                round_into(values, &mut row[..k]);
            }
            // SAFETY: the callers checked the CPU; the operands have the sizes `multiply`
            // asserts.
            unsafe { product(&lhs, m, &weights, &mut out) };
            let rounded = |v: f32| from_bf16(to_bf16(v)) as f64;
            for i in 0..m {
                for j in 0..n {
                    let expected = bias[j] as f64
                        + (0..k)
                            .map(|c| rounded(input[i * k + c]) * rounded(matrix[c * n + j]))
                            .sum::<f64>();
                    let got = out[i * n + j] as f64;
                    assert!(
                        (got - expected).abs() < 1e-4,
                        "[{m}x{k}x{n}] ({i}, {j}): {got} vs {expected}"
                    );
                }
            }
        }
    }

    #[test]
    #[cfg(target_arch = "x86_64")]
    fn tile_products_equal_the_rounded_operands_product() {
        if tiles_available() {
            assert_equals_the_rounded_operands_product(multiply_tiles);
        } else {
            crate::test_support::cannot_run(
                "this CPU has no AMX tiles (Intel Sapphire Rapids or newer)",
            );
        }
    }

    #[test]
    #[cfg(target_arch = "x86_64")]
    fn dot_products_equal_the_rounded_operands_product() {
        if dot_available() {
            assert_equals_the_rounded_operands_product(multiply_dot);
        } else {
            crate::test_support::cannot_run(
                "this CPU has no AVX-512 BF16 (AMD Zen 4, Intel Cooper Lake or newer)",
            );
        }
    }

    /// Where neither set of instructions can run, nothing claims one (and precision selection refuses bf16
    /// there, tested in `precision`).
    #[test]
    fn the_kernel_is_one_this_cpu_has() {
        match instructions() {
            Some(Bf16Instructions::AmxTiles) => assert!(tiles_available()),
            Some(Bf16Instructions::Avx512Dot) => assert!(dot_available() && !tiles_available()),
            None => assert!(!dot_available() && !tiles_available()),
        }
    }
}
