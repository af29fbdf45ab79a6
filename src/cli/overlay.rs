//! `--overlay`: the search image with every pose drawn as its rotated box, centre, an arrow
//! along the template's x axis (so the angle is visible) and the score.

use std::path::Path;

use image::{Rgb, RgbImage};
use imageproc::drawing::{draw_cross_mut, draw_filled_rect_mut, draw_line_segment_mut};
use imageproc::rect::Rect;

use super::CliError;
use crate::geometry::Pose;
use crate::imaging::RgbImage32;

const BOX: Rgb<u8> = Rgb([0, 230, 0]);
const ARROW: Rgb<u8> = Rgb([255, 40, 40]);
const LABEL: Rgb<u8> = Rgb([255, 255, 0]);

/// `poses` with the size (width, height) of the template each one is of.
pub fn save_overlay(
    image: &RgbImage32,
    poses: &[(Pose, (u32, u32))],
    path: &Path,
) -> Result<(), CliError> {
    let mut canvas = RgbImage::from_fn(image.width, image.height, |x, y| {
        let i = (y as usize * image.width as usize + x as usize) * 3;
        let byte = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
        Rgb([
            byte(image.pixels[i]),
            byte(image.pixels[i + 1]),
            byte(image.pixels[i + 2]),
        ])
    });
    // Thicker strokes on large frames so the drawing stays visible when scaled down.
    let thickness = (image.width.max(image.height) / 600).max(1) as i32;
    for (pose, (template_width, template_height)) in poses {
        let (tw, th) = (*template_width as f32, *template_height as f32);
        let corners = pose.corners(tw, th);
        for i in 0..4 {
            thick_line(
                &mut canvas,
                corners[i],
                corners[(i + 1) % 4],
                BOX,
                thickness,
            );
        }
        let tip = pose.map_point(tw / 2.0, 0.0);
        thick_line(&mut canvas, (pose.x, pose.y), tip, ARROW, thickness);
        // Arrow head: two short strokes back from the tip.
        for side in [-1.0f32, 1.0] {
            let back = pose.map_point(tw / 2.0 - tw / 8.0, side * th / 10.0);
            thick_line(&mut canvas, tip, back, ARROW, thickness);
        }
        draw_cross_mut(
            &mut canvas,
            ARROW,
            pose.x.round() as i32,
            pose.y.round() as i32,
        );
        let label = format!("{:.2}", pose.score);
        draw_text(
            &mut canvas,
            &label,
            pose.x.round() as i32 + 4,
            pose.y.round() as i32 + 4,
            thickness.max(1) as u32,
        );
    }
    canvas
        .save(path)
        .map_err(|e| CliError::io(path, std::io::Error::other(e)))
}

fn thick_line(
    canvas: &mut RgbImage,
    a: (f32, f32),
    b: (f32, f32),
    colour: Rgb<u8>,
    thickness: i32,
) {
    let half = thickness / 2;
    for dx in -half..=half {
        for dy in -half..=half {
            let off = |p: (f32, f32)| (p.0 + dx as f32, p.1 + dy as f32);
            draw_line_segment_mut(canvas, off(a), off(b), colour);
        }
    }
}

/// 8x8 bitmap text (font8x8), `scale` pixels per font dot, on a dark background.
fn draw_text(canvas: &mut RgbImage, text: &str, x: i32, y: i32, scale: u32) {
    use font8x8::UnicodeFonts;
    let side = 8 * scale;
    let width = side * text.chars().count() as u32;
    draw_filled_rect_mut(
        canvas,
        Rect::at(x - 1, y - 1).of_size(width + 2, side + 2),
        Rgb([0, 0, 0]),
    );
    for (k, ch) in text.chars().enumerate() {
        let Some(glyph) = font8x8::BASIC_FONTS.get(ch) else {
            continue;
        };
        for (row, bits) in glyph.iter().enumerate() {
            for col in 0..8 {
                if bits & (1 << col) != 0 {
                    let px = x + (k as u32 * side + col * scale) as i32;
                    let py = y + (row as u32 * scale) as i32;
                    draw_filled_rect_mut(canvas, Rect::at(px, py).of_size(scale, scale), LABEL);
                }
            }
        }
    }
}
