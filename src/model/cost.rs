//! Multiply-add count of one forward pass (convolutions and linears only, as the reference
//! README counts them), to turn a measured time into GFLOP/s.

/// Multiply-adds for a `height x width` search image and a `grid x grid` template.
pub fn multiply_adds(height: usize, width: usize, grid: usize) -> u64 {
    let backbone = |h: usize, w: usize| -> u64 {
        let (fh, fw) = (h / 4, w / 4);
        let p = (fh * fw) as u64;
        let stem = p * 96 * 3 * 16;
        let block = p * 96 * 49 + 2 * p * 96 * 384;
        stem + 3 * block
    };
    let (fh, fw) = ((height / 4) as u64, (width / 4) as u64);
    let k = (grid / 4) as u64;
    let quarter = fh * fw;
    let half = 4 * quarter;
    let full = 16 * quarter;
    let correlation = quarter * 96 * k * k;
    let fusion = quarter * 96 * 96 * 9;
    let conv1 = quarter * 192 * 96 * 9;
    let conv2 = half * 96 * 48 * 9;
    let heads = 5 * (full * 12 * 24 * 9 + full * 12);
    backbone(height, width) + backbone(grid, grid) + correlation + fusion + conv1 + conv2 + heads
}

#[cfg(test)]
mod tests {
    #[test]
    fn matches_the_reference_count() {
        // Reference README: 2.750 G multiply-adds at 224 / 36.
        let macs = super::multiply_adds(224, 224, 36) as f64 / 1e9;
        assert!((macs - 2.750).abs() < 0.002, "{macs}");
    }
}
