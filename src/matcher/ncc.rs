//! The classical baseline and weight-free fallback: exhaustive rotation x scale search with
//! zero-mean normalised cross-correlation over an image pyramid, the paper's NCC baseline.
//!
//! At a coarse pyramid level (template about 16 px) every angle (step from the template's
//! radius) and every scale pair of the requested range (10 % steps) is scored at every second
//! position with a sparse set of template points; the best few local maxima go to the same
//! refinement as the network's poses, at full resolution. Slow by design (seconds on large
//! images); it needs no weights and checks the network on the same pairs.

use rayon::prelude::*;

use crate::geometry::Pose;
use crate::imaging::GrayImage32;
use crate::refine::{Screened, TemplatePoints, Verifier};

use super::candidates::select;
use super::options::MatchOptions;

/// Finds the template in the image; poses in the public convention, best first.
pub fn ncc_match(template: &GrayImage32, image: &GrayImage32, options: &MatchOptions) -> Vec<Pose> {
    // Pyramid level: shrink until the template's shorter side is about 16 px.
    let mut level_template = template.clone();
    let mut level_image = image.clone();
    let mut factor = 1.0f32;
    while level_template.width.min(level_template.height) >= 32
        && level_image.width.min(level_image.height) >= 64
    {
        level_template = level_template.downsample();
        level_image = level_image.downsample();
        factor *= 2.0;
    }
    let points = TemplatePoints::new(&level_template, 12);
    // Scales relative to the registered template, the same at every level.
    let (lo, hi) = options.scale_range.map_or((1.0, 1.0), |r| (r.min, r.max));
    let scales: Vec<f32> = if hi > lo {
        let n = ((hi / lo).ln() / 1.1f32.ln()).ceil() as usize;
        (0..=n)
            .map(|k| lo * (hi / lo).powf(k as f32 / n as f32))
            .collect()
    } else {
        vec![lo]
    };
    let radius = (level_template.width.max(level_template.height) as f32) / 2.0;
    let angle_step = (1.5 / radius).to_degrees().clamp(2.0, 12.0);
    let angles: Vec<f32> = (0..(360.0 / angle_step).ceil() as usize)
        .map(|k| -180.0 + angle_step * (k as f32 + 0.5))
        .filter(|a| options.angle_range.is_none_or(|r| r.contains(*a)))
        .collect();
    // Best score per coarse position (stride 2), with the pose that gave it.
    let stride = 2;
    let (gw, gh) = (
        level_image.width.div_ceil(stride),
        level_image.height.div_ceil(stride),
    );
    let empty = (
        -1.0f32,
        Pose {
            x: 0.0,
            y: 0.0,
            angle_deg: 0.0,
            scale_x: 1.0,
            scale_y: 1.0,
            score: 0.0,
            network_score: 0.0,
        },
    );
    // One best-score map per angle, in parallel, then the best over angles.
    let per_angle: Vec<Vec<(f32, Pose)>> = angles
        .par_iter()
        .map(|&angle_deg| {
            let mut best = vec![empty; gw * gh];
            for &scale_x in &scales {
                for &scale_y in &scales {
                    for gy in 0..gh {
                        for gx in 0..gw {
                            let pose = Pose {
                                x: (gx * stride) as f32,
                                y: (gy * stride) as f32,
                                angle_deg,
                                scale_x,
                                scale_y,
                                score: 0.0,
                                network_score: 0.0,
                            };
                            let s = points.score(&level_image, &pose);
                            let cell = &mut best[gy * gw + gx];
                            if s > cell.0 {
                                *cell = (s, pose);
                            }
                        }
                    }
                }
            }
            best
        })
        .collect();
    let mut best = vec![empty; gw * gh];
    for map in per_angle {
        for (cell, candidate) in best.iter_mut().zip(map) {
            if candidate.0 > cell.0 {
                *cell = candidate;
            }
        }
    }
    // Local maxima of the best-score map, strongest first.
    let mut peaks: Vec<(f32, Pose)> = Vec::new();
    for gy in 0..gh {
        for gx in 0..gw {
            let s = best[gy * gw + gx].0;
            let is_max = (gy.saturating_sub(1)..(gy + 2).min(gh))
                .all(|y| (gx.saturating_sub(1)..(gx + 2).min(gw)).all(|x| best[y * gw + x].0 <= s));
            if is_max && s > 0.2 {
                peaks.push(best[gy * gw + gx]);
            }
        }
    }
    peaks.sort_by(|a, b| b.0.total_cmp(&a.0));
    peaks.truncate(4 * options.max_instances + 4);
    let verifier = Verifier::new(template, image, (lo, hi), |angle| {
        options
            .angle_range
            .is_none_or(|r| r.contains_within(angle, 5.0))
    });
    let poses: Vec<Pose> = peaks
        .into_par_iter()
        .map(|(score, coarse)| {
            // Back to full resolution: pixel centres scale as (x + 0.5)·f − 0.5.
            let initial = Pose {
                x: (coarse.x + 0.5) * factor - 0.5,
                y: (coarse.y + 0.5) * factor - 0.5,
                score: score.clamp(0.0, 1.0),
                ..coarse
            };
            if !options.refine {
                return initial; // scored by the coarse level's sparse ZNCC
            }
            // Refined, the score is the similarity at the refined pose, as for the network's
            // answers.
            let verified = verifier.confirm(
                &Screened {
                    pose: initial,
                    score,
                },
                &initial,
            );
            Pose {
                score: verified.score,
                ..verified.pose
            }
        })
        .collect();
    select(
        poses,
        options,
        template.width as f32,
        template.height as f32,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_a_rotated_copy_without_any_weights() {
        let (w, h) = (96usize, 96usize);
        let texture = |x: f32, y: f32| {
            0.5 + 0.2 * (x * 0.23 + y * 0.05).sin() * (y * 0.19).cos()
                + 0.15 * ((x * 0.07 - y * 0.13).sin() * 4.0).sin()
        };
        let image = GrayImage32 {
            width: w,
            height: h,
            values: (0..w * h)
                .map(|i| texture((i % w) as f32, (i / w) as f32))
                .collect(),
        };
        let truth = Pose {
            x: 47.2,
            y: 50.6,
            angle_deg: -62.0,
            scale_x: 1.0,
            scale_y: 1.0,
            score: 1.0,
            network_score: 0.0,
        };
        let values = (0..24 * 24)
            .map(|i| {
                let (x, y) = truth.map_point((i % 24) as f32 - 11.5, (i / 24) as f32 - 11.5);
                texture(x, y)
            })
            .collect();
        let template = GrayImage32 {
            width: 24,
            height: 24,
            values,
        };
        let options = MatchOptions {
            max_instances: 1,
            ..MatchOptions::default()
        };
        let found = ncc_match(&template, &image, &options);
        let p = found[0];
        assert!(
            (p.x - truth.x).abs() < 0.3 && (p.y - truth.y).abs() < 0.3,
            "{p:?}"
        );
        assert!(
            crate::geometry::angle_distance_deg(p.angle_deg, truth.angle_deg) < 0.5,
            "{p:?}"
        );
    }
}
