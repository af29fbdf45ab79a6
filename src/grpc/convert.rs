//! Between protobuf messages and the engine's types: images (encoded or raw camera buffers),
//! options with the proto's "zero means default" rule, poses, template metadata, and the one
//! table mapping [`EngineError`] to gRPC status codes.

use std::time::{Duration, Instant};

use tonic::Status;

use super::proto;
use crate::engine::store::{CalibrationRecord, StoreError, TemplateMeta};
use crate::engine::{EngineError, Roi};
use crate::geometry::{Pose, TemplateFrame, TemplateOrigin};
use crate::imaging::{DecodeError, ImageLimits, RgbImage32, decode_image_and_opacity};
use crate::matcher::{
    AngleRange, MaskError, MatchOptions, Method, Polarity, ScaleRange, TemplateMask, ValidOptions,
};
use crate::world::{CalibrationPoint, CalibrationSpec, WorldCalibration, WorldModel};

/// The one mapping from engine errors to gRPC status codes. Failures of ours (store, internal)
/// are logged in full and answered without server paths or details.
pub fn status_of(error: EngineError) -> Status {
    let message = bounded(error.to_string());
    match error {
        EngineError::InvalidArgument(_) | EngineError::Match(_) => {
            Status::invalid_argument(message)
        }
        EngineError::Unavailable(_) | EngineError::Store(StoreError::Unavailable(_)) => {
            Status::unavailable(message)
        }
        EngineError::NotFound(_) | EngineError::CalibrationNotFound(_) => {
            Status::not_found(message)
        }
        EngineError::AlreadyExists(_) | EngineError::CalibrationExists(_) => {
            Status::already_exists(message)
        }
        EngineError::ResourceExhausted(_) | EngineError::Store(StoreError::Full(_)) => {
            Status::resource_exhausted(message)
        }
        EngineError::DeadlineExceeded(_) => Status::deadline_exceeded(message),
        EngineError::Store(_) | EngineError::Internal(_) => {
            tracing::error!(error = %message.escape_debug(), "internal error");
            Status::internal(
                "internal error in the template store or a server task; the server log has the details",
            )
        }
    }
}

/// Longest status message sent: messages quote client input at most
/// [`crate::engine::MAX_QUOTED_CHARS`] characters, so only a bug could reach this; a status
/// travels in a header, and clients refuse large ones.
const MAX_STATUS_MESSAGE_BYTES: usize = 2048;

fn bounded(mut message: String) -> String {
    if message.len() > MAX_STATUS_MESSAGE_BYTES {
        let mut end = MAX_STATUS_MESSAGE_BYTES;
        while !message.is_char_boundary(end) {
            end -= 1;
        }
        message.truncate(end);
        message.push('…');
    }
    message
}

/// Decodes a request's image. `what` names the field in errors ("image", "template image");
/// `limits` are checked from the header (or the raw buffer's fields) before any pixel buffer
/// exists.
pub fn image_from_proto(
    image: Option<proto::Image>,
    what: &str,
    limits: ImageLimits,
) -> Result<RgbImage32, EngineError> {
    image_and_opacity_from_proto(image, what, limits).map(|(image, _)| image)
}

/// [`image_from_proto`], and which pixels are opaque where an encoded image has transparent
/// ones (see [`crate::imaging::decode_image_and_opacity`]); raw images have no alpha.
pub fn image_and_opacity_from_proto(
    image: Option<proto::Image>,
    what: &str,
    limits: ImageLimits,
) -> Result<(RgbImage32, Option<Vec<bool>>), EngineError> {
    let invalid = |m: String| EngineError::InvalidArgument(m);
    let data = image.and_then(|i| i.data).ok_or_else(|| {
        invalid(format!(
            "{what} is missing: set {what}.encoded (PNG/JPEG/BMP/TIFF/PNM bytes) or {what}.raw"
        ))
    })?;
    match data {
        proto::image::Data::Encoded(bytes) => decode_image_and_opacity(&bytes, what, limits)
            .map_err(|e: DecodeError| invalid(e.to_string())),
        proto::image::Data::Raw(raw) => raw_to_rgb(&raw, what, limits).map(|image| (image, None)),
    }
}

/// A registration's template and mask: the request's `mask` image (black = ignore, anything
/// else = use), or else the template's own transparent pixels; checked against the template's
/// size and for enough used pixels.
pub fn template_from_proto(
    image: Option<proto::Image>,
    mask: Option<proto::Image>,
    limits: ImageLimits,
) -> Result<(RgbImage32, Option<TemplateMask>), EngineError> {
    let invalid = |field: &str, e: MaskError| EngineError::InvalidArgument(format!("{field}: {e}"));
    let (template, opaque) = image_and_opacity_from_proto(image, "template image", limits)?;
    let mask = match (mask.filter(|m| m.data.is_some()), opaque) {
        (Some(mask), _) => {
            let mask_image = image_from_proto(Some(mask), "mask", limits)?;
            let mask = TemplateMask::from_image(&mask_image).map_err(|e| invalid("mask", e))?;
            mask.check_fits(template.width, template.height)
                .map_err(|e| invalid("mask", e))?;
            Some(mask)
        }
        (None, Some(opaque)) => Some(
            TemplateMask::new(template.width, template.height, opaque)
                .map_err(|e| invalid("template image (its alpha channel)", e))?,
        ),
        (None, None) => None,
    };
    Ok((template, mask))
}

fn raw_to_rgb(
    raw: &proto::RawImage,
    what: &str,
    limits: ImageLimits,
) -> Result<RgbImage32, EngineError> {
    use proto::raw_image::Format;
    let invalid = |m: String| Err(EngineError::InvalidArgument(format!("{what}.raw: {m}")));
    let (w, h) = (raw.width, raw.height);
    if w == 0 || h == 0 {
        return invalid(format!("{w}x{h} is empty; set width and height"));
    }
    limits
        .check(&format!("{what}.raw"), w, h)
        .map_err(|e| EngineError::InvalidArgument(e.to_string()))?;
    let format = Format::try_from(raw.format).unwrap_or(Format::Unspecified);
    let bytes_per_pixel = match format {
        Format::Gray8 => 1,
        Format::Rgb8 | Format::Bgr8 => 3,
        Format::Gray16 => 2,
        Format::Unspecified => {
            return invalid(format!(
                "format {} is not set or unknown; use GRAY8, RGB8, BGR8 or GRAY16",
                raw.format
            ));
        }
    };
    let expected = w as u64 * h as u64 * bytes_per_pixel;
    if raw.pixels.len() as u64 != expected {
        return invalid(format!(
            "{} bytes of pixels, but {w}x{h} {format:?} needs {expected} (rows packed, no padding)",
            raw.pixels.len(),
            format = format.as_str_name()
        ));
    }
    let p = &raw.pixels;
    let scale8 = 1.0 / 255.0;
    let values: Vec<f32> = match format {
        Format::Gray8 => p.iter().flat_map(|&g| [g as f32 * scale8; 3]).collect(),
        Format::Rgb8 => p.iter().map(|&v| v as f32 * scale8).collect(),
        Format::Bgr8 => p
            .chunks_exact(3)
            .flat_map(|c| [c[2], c[1], c[0]].map(|v| v as f32 * scale8))
            .collect(),
        Format::Gray16 => p
            .chunks_exact(2)
            .flat_map(|c| [u16::from_le_bytes([c[0], c[1]]) as f32 / 65535.0; 3])
            .collect(),
        Format::Unspecified => unreachable!("rejected above"),
    };
    Ok(RgbImage32::new(w, h, values))
}

/// Options with `defaults` (the service's settings) for zero values; anything out of range is
/// an error that names the field. Every field of the message is taken apart here by name, so a
/// field added to the proto does not compile until it is handled.
/// A request's options as the engine takes them: the matcher's options, the region searched
/// and the calibration the poses are placed in the world with.
#[derive(Debug)]
pub struct RequestedMatch {
    pub options: ValidOptions,
    pub roi: Option<Roi>,
    pub calibration_id: Option<String>,
}

pub fn options_from_proto(
    options: Option<proto::MatchOptions>,
    defaults: &MatchOptions,
) -> Result<RequestedMatch, EngineError> {
    let proto::MatchOptions {
        max_instances,
        min_score,
        max_overlap,
        angle_start_deg,
        angle_extent_deg,
        scale_min,
        scale_max,
        no_refine,
        roi,
        candidate_threshold,
        max_candidates,
        method,
        no_classical_fallback,
        polarity,
        timeout_ms,
        calibration_id,
        suppress_across_templates,
    } = options.unwrap_or_default();
    let invalid = |m: String| Err(EngineError::InvalidArgument(m));
    let finite = [
        ("min_score", min_score),
        ("candidate_threshold", candidate_threshold),
        ("max_overlap", max_overlap),
        ("angle_start_deg", angle_start_deg),
        ("angle_extent_deg", angle_extent_deg),
        ("scale_min", scale_min),
        ("scale_max", scale_max),
    ];
    if let Some((name, value)) = finite.iter().find(|(_, v)| !v.is_finite()) {
        return invalid(format!("options.{name} is {value}; give a finite number"));
    }
    if !(-360.0..=360.0).contains(&angle_start_deg) {
        return invalid(format!(
            "options.angle_start_deg {angle_start_deg} is out of range: give degrees in [-360, 360]"
        ));
    }
    let angle_range = match angle_extent_deg {
        0.0 => None,
        e if !(0.0..=360.0).contains(&e) => {
            return invalid(format!(
                "options.angle_extent_deg {e} is invalid: use (0, 360], or 0 for every angle"
            ));
        }
        e => Some(AngleRange {
            start_deg: angle_start_deg,
            extent_deg: e,
        }),
    };
    let scale_range = match (scale_min, scale_max) {
        (a, b) if a == 0.0 && b == 0.0 => None,
        (a, b) if a == 0.0 || b == 0.0 => {
            return invalid(format!(
                "options.scale_min {a} / scale_max {b}: give both (e.g. 0.8 and 1.25) or neither"
            ));
        }
        (a, b) => Some(ScaleRange::new(a, b).map_err(|m| {
            EngineError::InvalidArgument(format!("options.scale_min/scale_max: {m}"))
        })?),
    };
    let or_default = |given: f32, default: f32| if given == 0.0 { default } else { given };
    let options = MatchOptions {
        max_instances: match max_instances {
            0 => defaults.max_instances,
            n => n as usize,
        },
        min_score: if min_score == 0.0 {
            defaults.min_score
        } else {
            Some(min_score)
        },
        max_overlap: or_default(max_overlap, defaults.max_overlap),
        candidate_threshold: or_default(candidate_threshold, defaults.candidate_threshold),
        max_candidates: match max_candidates {
            0 => defaults.max_candidates,
            n => n as usize,
        },
        angle_range,
        scale_range,
        verify: !no_refine,
        classical_fallback: defaults.classical_fallback && !no_classical_fallback,
        method: match proto::Method::try_from(method) {
            Ok(proto::Method::Unspecified | proto::Method::Tdcm) => Method::Tdcm,
            Ok(proto::Method::Ncc) => Method::Ncc,
            Err(_) => {
                return invalid(format!(
                    "options.method {method} is unknown: use METHOD_TDCM (1) or METHOD_NCC (2)"
                ));
            }
        },
        timeout_ms: timeout_ms.or(defaults.timeout_ms),
        covered_parts: None,
        suppress_across_templates,
        polarity: match proto::Polarity::try_from(polarity) {
            Ok(proto::Polarity::Unspecified) => defaults.polarity,
            Ok(proto::Polarity::Same) => Polarity::Same,
            Ok(proto::Polarity::Reversed) => Polarity::Reversed,
            Ok(proto::Polarity::Either) => Polarity::Either,
            Err(_) => {
                return invalid(format!(
                    "options.polarity {polarity} is unknown: use POLARITY_SAME (1), \
                     POLARITY_REVERSED (2) or POLARITY_EITHER (3)"
                ));
            }
        },
    };
    let options = options
        .validate()
        .map_err(|m| EngineError::InvalidArgument(format!("options.{m}")))?;
    let roi = roi.and_then(|r| {
        (r.width != 0 || r.height != 0 || r.x != 0 || r.y != 0).then_some(Roi {
            x: r.x,
            y: r.y,
            width: r.width,
            height: r.height,
        })
    });
    Ok(RequestedMatch {
        options,
        roi,
        calibration_id: (!calibration_id.is_empty()).then_some(calibration_id),
    })
}

/// A pose of `template`, with its transform, where the template's reference point lands and,
/// with a calibration, where that lies in the world.
pub fn pose_to_proto(
    pose: &Pose,
    template_id: &str,
    template: &TemplateFrame,
    calibration: Option<&WorldCalibration>,
) -> proto::Pose {
    let (origin_x, origin_y) = template.origin_in_image(pose);
    let world = calibration.map(|c| c.place(pose, template));
    proto::Pose {
        transform: template.transform(pose).to_vec(),
        origin_x,
        origin_y,
        world_x: world.map(|w| w.x),
        world_y: world.map(|w| w.y),
        world_angle_deg: world.map(|w| w.angle_deg),
        x: pose.x,
        y: pose.y,
        angle_deg: pose.angle_deg,
        scale_x: pose.scale_x,
        scale_y: pose.scale_y,
        score: pose.score,
        network_score: pose.network_score,
        template_id: template_id.to_owned(),
    }
}

/// A registration's origin: both coordinates or neither, checked against the template's size.
pub fn origin_from_proto(
    x: Option<f32>,
    y: Option<f32>,
    width: u32,
    height: u32,
) -> Result<Option<TemplateOrigin>, EngineError> {
    match (x, y) {
        (None, None) => Ok(None),
        (Some(x), Some(y)) => TemplateOrigin::new(x, y, width, height)
            .map(Some)
            .map_err(|m| EngineError::InvalidArgument(format!("origin_x/origin_y: {m}"))),
        _ => Err(EngineError::InvalidArgument(
            "origin_x/origin_y: give both (template pixel column and row) or neither (the template centre)".into(),
        )),
    }
}

/// The points and unit as sent; [`crate::world::WorldCalibration::fit`] checks them.
pub fn calibration_spec_from_proto(
    points: &[proto::CalibrationPoint],
    unit: &str,
) -> CalibrationSpec {
    CalibrationSpec {
        points: points
            .iter()
            .map(|p| CalibrationPoint {
                image: [p.image_x, p.image_y],
                world: [p.world_x, p.world_y],
            })
            .collect(),
        unit: unit.to_owned(),
    }
}

pub fn calibration_info(
    record: CalibrationRecord,
    fitted: &WorldCalibration,
) -> proto::CalibrationInfo {
    proto::CalibrationInfo {
        calibration_id: record.calibration_id,
        points: record
            .spec
            .points
            .iter()
            .map(|p| proto::CalibrationPoint {
                image_x: p.image[0],
                image_y: p.image[1],
                world_x: p.world[0],
                world_y: p.world[1],
            })
            .collect(),
        unit: record.spec.unit,
        model: match fitted.model() {
            WorldModel::Affine => proto::calibration_info::Model::Affine,
            WorldModel::Homography => proto::calibration_info::Model::Homography,
        } as i32,
        rms_residual: fitted.rms_residual(),
        created_unix_ms: record.created_unix_ms,
        updated_unix_ms: record.updated_unix_ms,
        version: record.version,
    }
}

pub fn template_info(meta: TemplateMeta) -> proto::TemplateInfo {
    proto::TemplateInfo {
        template_id: meta.template_id,
        width: meta.width,
        height: meta.height,
        labels: meta.labels.into_iter().collect(),
        content_sha256: meta.content_sha256,
        created_unix_ms: meta.created_unix_ms,
        updated_unix_ms: meta.updated_unix_ms,
        version: meta.version,
        origin_x: meta.origin.map(|o| o.x),
        origin_y: meta.origin.map(|o| o.y),
        image: None,
        mask: None,
    }
}

/// The request's deadline from its `grpc-timeout` header ("100m" = 100 ms; units H M S m u n).
pub fn deadline_of(metadata: &tonic::metadata::MetadataMap, received: Instant) -> Option<Instant> {
    let value = metadata.get("grpc-timeout")?.to_str().ok()?;
    let (digits, unit) = value.split_at(value.len().checked_sub(1)?);
    let amount: u64 = digits.parse().ok()?;
    let timeout = match unit {
        "H" => Duration::from_secs(amount.saturating_mul(3600)),
        "M" => Duration::from_secs(amount.saturating_mul(60)),
        "S" => Duration::from_secs(amount),
        "m" => Duration::from_millis(amount),
        "u" => Duration::from_micros(amount),
        "n" => Duration::from_nanos(amount),
        _ => return None,
    };
    received.checked_add(timeout)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// At most 100 pixels, any side.
    const TINY: ImageLimits = ImageLimits {
        max_pixels: 100,
        min_side: 1,
        max_side: u32::MAX,
    };

    #[test]
    fn store_failures_are_internal_and_keep_server_paths_to_the_log() {
        let error = EngineError::from(crate::engine::store::StoreError::Io {
            path: "/srv/secret/templates/part.json".into(),
            source: std::io::Error::other("disk full"),
        });
        let status = status_of(error);
        assert_eq!(status.code(), tonic::Code::Internal);
        assert!(
            !status.message().contains("/srv/secret"),
            "{}",
            status.message()
        );
        let status = status_of(EngineError::from(
            crate::matcher::MatchError::TemplateSize {
                width: 4,
                height: 4,
            },
        ));
        assert_eq!(status.code(), tonic::Code::InvalidArgument);
        assert!(status.message().contains("4x4"));
        let status = status_of(EngineError::from(StoreError::Unavailable(
            "connection refused".into(),
        )));
        assert_eq!(status.code(), tonic::Code::Unavailable);
        assert!(
            status.message().contains("unreachable") && status.message().contains("cached"),
            "{}",
            status.message()
        );
    }

    fn raw(
        width: u32,
        height: u32,
        format: proto::raw_image::Format,
        pixels: Vec<u8>,
    ) -> proto::Image {
        proto::Image {
            data: Some(proto::image::Data::Raw(proto::RawImage {
                width,
                height,
                format: format as i32,
                pixels,
            })),
        }
    }

    #[test]
    fn raw_formats_agree_with_each_other() {
        use proto::raw_image::Format;
        let rgb = image_from_proto(
            Some(raw(2, 1, Format::Rgb8, vec![10, 20, 30, 40, 50, 60])),
            "image",
            TINY,
        )
        .unwrap();
        let bgr = image_from_proto(
            Some(raw(2, 1, Format::Bgr8, vec![30, 20, 10, 60, 50, 40])),
            "image",
            TINY,
        )
        .unwrap();
        assert_eq!(rgb.pixels, bgr.pixels);
        let g8 =
            image_from_proto(Some(raw(1, 1, Format::Gray8, vec![255])), "image", TINY).unwrap();
        let g16 = image_from_proto(
            Some(raw(1, 1, Format::Gray16, vec![255, 255])),
            "image",
            TINY,
        )
        .unwrap();
        assert_eq!(g8.pixels, vec![1.0; 3]);
        assert_eq!(g16.pixels, vec![1.0; 3]);
    }

    #[test]
    fn bad_raw_images_say_what_is_wrong() {
        use proto::raw_image::Format;
        let err = |image| {
            image_from_proto(Some(image), "image", TINY)
                .unwrap_err()
                .to_string()
        };
        assert!(err(raw(2, 2, Format::Rgb8, vec![0; 5])).contains("needs 12"));
        assert!(err(raw(2, 2, Format::Unspecified, vec![0; 4])).contains("GRAY8"));
        assert!(err(raw(20, 20, Format::Gray8, vec![0; 400])).contains("limit"));
        assert!(err(raw(0, 2, Format::Gray8, vec![])).contains("empty"));
        assert!(
            image_from_proto(None, "image", TINY)
                .unwrap_err()
                .to_string()
                .contains("missing")
        );
    }

    #[test]
    fn zero_options_are_defaults_and_absurd_ones_are_refused() {
        let RequestedMatch {
            options: o, roi, ..
        } = options_from_proto(None, &MatchOptions::default()).unwrap();
        assert_eq!(o, ValidOptions::default());
        assert!(roi.is_none());
        let bad = |o: proto::MatchOptions| {
            options_from_proto(Some(o), &MatchOptions::default())
                .unwrap_err()
                .to_string()
        };
        assert!(
            bad(proto::MatchOptions {
                min_score: 1.5,
                ..Default::default()
            })
            .contains("min_score")
        );
        assert!(
            bad(proto::MatchOptions {
                max_instances: 5000,
                ..Default::default()
            })
            .contains("max_instances")
        );
        assert!(
            bad(proto::MatchOptions {
                angle_extent_deg: 400.0,
                ..Default::default()
            })
            .contains("angle_extent_deg")
        );
        assert!(
            bad(proto::MatchOptions {
                angle_start_deg: 1e30,
                angle_extent_deg: 20.0,
                ..Default::default()
            })
            .contains("angle_start_deg")
        );
        assert!(
            bad(proto::MatchOptions {
                scale_min: 0.5,
                ..Default::default()
            })
            .contains("both")
        );
        assert!(
            bad(proto::MatchOptions {
                scale_min: 3.0,
                scale_max: 2.0,
                ..Default::default()
            })
            .contains("scale")
        );
        assert!(
            bad(proto::MatchOptions {
                min_score: f32::NAN,
                ..Default::default()
            })
            .contains("finite")
        );
    }

    #[test]
    fn polarity_comes_from_the_request_or_else_the_server_and_unknown_values_are_refused() {
        let polarity = |requested: i32, server: Polarity| {
            let defaults = MatchOptions {
                polarity: server,
                ..MatchOptions::default()
            };
            let request = proto::MatchOptions {
                polarity: requested,
                ..Default::default()
            };
            options_from_proto(Some(request), &defaults).map(|r| r.options.polarity)
        };
        assert_eq!(polarity(0, Polarity::Same).unwrap(), Polarity::Same);
        assert_eq!(polarity(0, Polarity::Either).unwrap(), Polarity::Either);
        assert_eq!(polarity(2, Polarity::Same).unwrap(), Polarity::Reversed);
        assert_eq!(polarity(3, Polarity::Same).unwrap(), Polarity::Either);
        assert_eq!(polarity(1, Polarity::Either).unwrap(), Polarity::Same);
        let refused = polarity(9, Polarity::Same).unwrap_err().to_string();
        assert!(refused.contains("options.polarity 9"), "{refused}");
    }

    #[test]
    fn the_classical_fallback_is_on_unless_the_request_or_the_server_switches_it_off() {
        let fallback = |no_classical_fallback: bool, server: bool| {
            let defaults = MatchOptions {
                classical_fallback: server,
                ..MatchOptions::default()
            };
            let request = proto::MatchOptions {
                no_classical_fallback,
                ..Default::default()
            };
            let options = options_from_proto(Some(request), &defaults)
                .unwrap()
                .options;
            options.classical_fallback
        };
        assert!(fallback(false, true));
        assert!(!fallback(true, true));
        assert!(!fallback(false, false));
        assert!(!fallback(true, false));
    }

    #[test]
    fn grpc_timeout_header_becomes_a_deadline() {
        let now = Instant::now();
        let mut md = tonic::metadata::MetadataMap::new();
        assert_eq!(deadline_of(&md, now), None);
        md.insert("grpc-timeout", "250m".parse().unwrap());
        assert_eq!(
            deadline_of(&md, now),
            Some(now + Duration::from_millis(250))
        );
        md.insert("grpc-timeout", "2S".parse().unwrap());
        assert_eq!(deadline_of(&md, now), Some(now + Duration::from_secs(2)));
    }
}
