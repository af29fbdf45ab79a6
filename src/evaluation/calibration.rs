//! What `posematch eval` reports beside the paper's metrics: how often a verified answer is
//! right at each score (the calibration that chose the default `min_score`), and which pairs a
//! path won or lost against the network's own answer.

use super::PairError;

/// How often a verified answer is right, by its score: every answer of the verified path
/// (whatever `min_score`), counted per score band.
#[derive(Debug, Default, serde::Serialize)]
pub struct Calibration {
    /// Per band of [`Calibration::BANDS`]: answers, and how many of them were right.
    answers: [usize; 9],
    right: [usize; 9],
}

impl Calibration {
    /// Lower edges of the score bands (the last band ends at 1).
    const BANDS: [f32; 9] = [0.0, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95];

    pub fn add(&mut self, score: f32, right: bool) {
        let band = Self::BANDS
            .iter()
            .rposition(|&edge| score >= edge)
            .unwrap_or(0);
        self.answers[band] += 1;
        self.right[band] += usize::from(right);
    }

    /// The band table with the share of right answers per band and, cumulatively, among all
    /// answers at or above the band's lower edge (precision at that `min_score`).
    pub fn table(&self) -> String {
        let mut lines = vec![
            "score calibration (every verified answer, before min_score):".to_string(),
            format!(
                "| {:<11} | {:>7} | {:>7} | {:>10} | {:>16} |",
                "score", "answers", "right", "share right", "right at >= lower"
            ),
        ];
        for (i, &edge) in Self::BANDS.iter().enumerate() {
            let upper = Self::BANDS.get(i + 1).copied().unwrap_or(1.0);
            let (above_answers, above_right): (usize, usize) = (i..Self::BANDS.len())
                .map(|j| (self.answers[j], self.right[j]))
                .fold((0, 0), |(a, r), (x, y)| (a + x, r + y));
            let share = |r: usize, a: usize| {
                if a == 0 {
                    "-".to_string()
                } else {
                    format!("{:.1}%", 100.0 * r as f32 / a as f32)
                }
            };
            lines.push(format!(
                "| {:<11} | {:>7} | {:>7} | {:>10} | {:>16} |",
                format!("{edge:.2}-{upper:.2}"),
                self.answers[i],
                self.right[i],
                share(self.right[i], self.answers[i]),
                share(above_right, above_answers)
            ));
        }
        lines.join("\n")
    }
}

/// How many of the network's successes another path lost, and how many failures it turned into
/// successes (IoU >= 0.5), pair by pair.
pub fn path_changes(
    coarse: &[(Option<PairError>, f64)],
    refined: &[(Option<PairError>, f64)],
) -> (usize, usize) {
    let success = |e: &Option<PairError>| e.as_ref().is_some_and(|e| e.iou >= 0.5);
    coarse
        .iter()
        .zip(refined)
        .fold((0, 0), |(lost, gained), ((c, _), (r, _))| {
            (
                lost + usize::from(success(c) && !success(r)),
                gained + usize::from(!success(c) && success(r)),
            )
        })
}
