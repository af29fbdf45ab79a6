//! Matching registered templates: the image cropped to its region of interest, sizes checked,
//! the work queued for the batching model thread (or, for the classical method, run on a
//! blocking thread one search at a time), poses moved back into the full image. Several
//! templates in one request share the decoded image and are queued together, so the model
//! thread batches them (and runs the search backbone once for templates of equal area).

use std::sync::Arc;
use std::time::Instant;

use tokio::sync::oneshot;

use futures_util::future::try_join_all;

use super::batcher::{BatchError, MatchWork, SubmitError};
use super::{Engine, EngineError};
use crate::geometry::{Pose, TemplateFrame};
use crate::imaging::{GrayImage32, RgbImage32};
use crate::matcher::selection::suppress_across_templates;
use crate::matcher::{EncodedTemplate, MatchTimings, Method, ValidOptions, classical};

/// A rectangle of the search image to restrict the search to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Roi {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

/// The answer to one match.
#[derive(Debug, Clone)]
pub struct MatchAnswer {
    /// In the full image's coordinates, best first.
    pub poses: Vec<Pose>,
    pub timings: MatchTimings,
    pub queue_ms: f64,
    pub batch_size: usize,
    /// The options' time limit came first ([`crate::matcher::MatchOutcome::timed_out`]).
    pub timed_out: bool,
    /// The registered template's size (what the poses' scales refer to) and reference point.
    pub template: TemplateFrame,
}

impl Engine {
    /// Finds the template in `image` (optionally only inside `roi`). Past `deadline` the
    /// request is dropped unanswered (DEADLINE_EXCEEDED); at `answer_by` (the options'
    /// `timeout_ms` after the request arrived) the network path answers with what it has.
    pub async fn match_image(
        &self,
        template_id: &str,
        image: RgbImage32,
        options: ValidOptions,
        roi: Option<Roi>,
        deadline: Option<Instant>,
        answer_by: Option<Instant>,
    ) -> Result<MatchAnswer, EngineError> {
        let ids = [template_id.to_owned()];
        let mut answers = self
            .match_templates(&ids, image, options, roi, deadline, answer_by)
            .await?;
        Ok(answers.pop().expect("one template in, one answer out"))
    }

    /// [`Engine::match_image`] for each of `template_ids` (1..=[`MAX_TEMPLATES_PER_MATCH`],
    /// no ID twice) in one image: one answer per template, in their order, each with the same
    /// options (`max_instances` counts per template). Every ID is looked up before any work
    /// starts, so an unknown one fails the request without a search.
    pub async fn match_templates(
        &self,
        template_ids: &[String],
        image: RgbImage32,
        options: ValidOptions,
        roi: Option<Roi>,
        deadline: Option<Instant>,
        answer_by: Option<Instant>,
    ) -> Result<Vec<MatchAnswer>, EngineError> {
        check_template_ids(template_ids)?;
        let mut templates = Vec::with_capacity(template_ids.len());
        for id in template_ids {
            templates.push(self.encoded_template(id).await?);
        }
        let (image, offset) = match roi {
            None => (image, (0.0, 0.0)),
            Some(roi) => {
                check_roi(&roi, image.width, image.height)?;
                let cropped = image.crop(roi.x, roi.y, roi.width, roi.height);
                (cropped, (roi.x as f32, roi.y as f32))
            }
        };
        for template in &templates {
            crate::matcher::check_pair_sizes(
                template.width,
                template.height,
                image.width,
                image.height,
            )?;
        }
        let image = Arc::new(image);
        let mut answers = match options.method {
            // All searches are queued before any is awaited, so they meet in one batch.
            Method::Tdcm => {
                try_join_all(templates.into_iter().map(|template| {
                    self.match_network(
                        template,
                        Arc::clone(&image),
                        options.clone(),
                        deadline,
                        answer_by,
                    )
                }))
                .await?
            }
            Method::Ncc => {
                let mut answers = Vec::with_capacity(templates.len());
                for template in templates {
                    answers.push(
                        self.match_classical(
                            template,
                            Arc::clone(&image),
                            &options,
                            deadline,
                            answer_by,
                        )
                        .await?,
                    );
                }
                answers
            }
        };
        if options.suppress_across_templates && answers.len() > 1 {
            suppress_overlaps_across(&mut answers, options.max_overlap);
        }
        for pose in answers.iter_mut().flat_map(|answer| &mut answer.poses) {
            pose.x += offset.0;
            pose.y += offset.1;
        }
        Ok(answers)
    }

    /// The network's path: its compute budget checked, then queued for the batching model
    /// thread.
    async fn match_network(
        &self,
        template: Arc<EncodedTemplate>,
        image: Arc<RgbImage32>,
        options: ValidOptions,
        deadline: Option<Instant>,
        answer_by: Option<Instant>,
    ) -> Result<MatchAnswer, EngineError> {
        let frame = template.frame();
        crate::matcher::check_network_budget(
            template.width,
            template.height,
            image.width,
            image.height,
            &options,
            self.max_network_pixels,
            crate::matcher::plan::DEFAULT_GRID_SCALE,
        )?;
        let (reply, answer) = oneshot::channel();
        self.batcher
            .submit(MatchWork {
                template,
                image,
                options,
                deadline,
                answer_by,
                reply,
                span: tracing::Span::current(),
            })
            .map_err(|e| match e {
                SubmitError::Full(e) => EngineError::ResourceExhausted(e.to_string()),
                SubmitError::Gone(e) => EngineError::Unavailable(e.to_string()),
            })?;
        let answer = answer
            .await
            .map_err(|_| EngineError::Unavailable("the model thread stopped".into()))?
            .map_err(|e| match e {
                BatchError::Match(e) => EngineError::from(e),
                BatchError::DeadlineExceeded => EngineError::DeadlineExceeded(e.to_string()),
                BatchError::ModelFailed => EngineError::Internal(e.to_string()),
            })?;
        Ok(MatchAnswer {
            poses: answer.outcome.poses,
            timings: answer.outcome.timings,
            queue_ms: answer.queue_ms,
            batch_size: answer.batch_size,
            timed_out: answer.outcome.timed_out,
            template: frame,
        })
    }

    /// The classical matcher on a blocking thread, one search at a time; its cost is checked
    /// before it waits.
    async fn match_classical(
        &self,
        template: Arc<EncodedTemplate>,
        image: Arc<RgbImage32>,
        options: &ValidOptions,
        deadline: Option<Instant>,
        answer_by: Option<Instant>,
    ) -> Result<MatchAnswer, EngineError> {
        let frame = template.frame();
        classical::check_work(
            template.width,
            template.height,
            image.width,
            image.height,
            options,
        )?;
        let options = options.clone();
        let queued = Instant::now();
        let permit = self.classical.acquire();
        let _permit = match deadline {
            None => permit.await,
            Some(deadline) => tokio::time::timeout_at(deadline.into(), permit)
                .await
                .map_err(|_| {
                    EngineError::DeadlineExceeded(
                        "the request's deadline passed while it waited for the classical matcher"
                            .into(),
                    )
                })?,
        }
        .map_err(|_| EngineError::Unavailable("the engine is shutting down".into()))?;
        let queue_ms = queued.elapsed().as_secs_f64() * 1e3;
        let start = Instant::now();
        let found = super::blocking(move || {
            classical::ncc_match_until(
                &template.gray,
                &GrayImage32::from_rgb(&image),
                &options,
                answer_by,
            )
        })
        .await?;
        Ok(MatchAnswer {
            poses: found.poses,
            timings: MatchTimings {
                refine_ms: start.elapsed().as_secs_f64() * 1e3,
                ..MatchTimings::default()
            },
            queue_ms,
            batch_size: 1,
            timed_out: found.timed_out,
            template: frame,
        })
    }
}

/// [`suppress_across_templates`] over one request's answers (one per template, each best
/// first): a pose that a better answer of another template overlaps by more than `max_overlap`
/// is removed from its template's answer.
fn suppress_overlaps_across(answers: &mut [MatchAnswer], max_overlap: f32) {
    let sizes: Vec<(f32, f32)> = answers
        .iter()
        .map(|a| (a.template.width as f32, a.template.height as f32))
        .collect();
    let found: Vec<(usize, Pose)> = answers
        .iter_mut()
        .enumerate()
        .flat_map(|(index, answer)| {
            std::mem::take(&mut answer.poses)
                .into_iter()
                .map(move |pose| (index, pose))
        })
        .collect();
    // Kept best first overall, hence best first within each template.
    for (index, pose) in suppress_across_templates(found, &sizes, max_overlap) {
        answers[index].poses.push(pose);
    }
}

/// The most templates one match request may name: each is a full search of the image.
pub const MAX_TEMPLATES_PER_MATCH: usize = 16;

fn check_template_ids(ids: &[String]) -> Result<(), EngineError> {
    if ids.is_empty() {
        return Err(EngineError::InvalidArgument(
            "no template named; give the ID of a registered template".into(),
        ));
    }
    if ids.len() > MAX_TEMPLATES_PER_MATCH {
        return Err(EngineError::InvalidArgument(format!(
            "{} templates named; one request may search for at most {MAX_TEMPLATES_PER_MATCH}",
            ids.len()
        )));
    }
    for (i, id) in ids.iter().enumerate() {
        if id.is_empty() {
            return Err(EngineError::InvalidArgument(
                "a template ID is empty; give the ID of a registered template".into(),
            ));
        }
        if ids[..i].contains(id) {
            return Err(EngineError::InvalidArgument(format!(
                "template {} is named twice; name each template once",
                super::quoted(id)
            )));
        }
    }
    Ok(())
}

fn check_roi(roi: &Roi, width: u32, height: u32) -> Result<(), EngineError> {
    let inside = roi.width > 0
        && roi.height > 0
        && roi.x as u64 + roi.width as u64 <= width as u64
        && roi.y as u64 + roi.height as u64 <= height as u64;
    if inside {
        Ok(())
    } else {
        Err(EngineError::InvalidArgument(format!(
            "roi x={} y={} {}x{} does not lie inside the {width}x{height} image",
            roi.x, roi.y, roi.width, roi.height
        )))
    }
}
