//! `posematch.v1.PoseMatcher`: each RPC converts its request, calls the engine, converts the
//! answer, and records one span, one request count and one latency sample.

use std::pin::Pin;
use std::sync::{Arc, OnceLock};
use std::time::Instant;

use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};
use tracing::Instrument;

use super::convert::{
    RequestedMatch, calibration_info, calibration_spec_from_proto, deadline_of, image_from_proto,
    options_from_proto, origin_from_proto, pose_to_proto, status_of, template_from_proto,
    template_info,
};
use super::proto::{self, pose_matcher_server::PoseMatcher};
use crate::engine::{Engine, EngineError, MatchAnswer, Metrics, RegisteredTemplate, quoted};
use crate::imaging::RgbImage32;
use crate::matcher::{MatchOptions, TEMPLATE_LIMITS, TemplateMask, search_limits};

pub struct Api {
    engine: Arc<OnceLock<Arc<Engine>>>,
    metrics: Metrics,
    decoder: Arc<ImageDecoder>,
    /// What a Match request's zero-valued options mean (from the settings).
    match_defaults: MatchOptions,
}

/// Decodes request images with bounded memory: sizes are checked from the header before any
/// pixel buffer exists, and at most `max_concurrent_decodes` images are decoded at once (the
/// rest wait their turn, holding only their encoded bytes).
pub struct ImageDecoder {
    max_image_pixels: u64,
    permits: tokio::sync::Semaphore,
}

impl ImageDecoder {
    pub fn new(max_image_pixels: u64, max_concurrent_decodes: usize) -> Self {
        Self {
            max_image_pixels,
            permits: tokio::sync::Semaphore::new(max_concurrent_decodes.max(1)),
        }
    }

    /// A search image, within `max_image_pixels`.
    async fn search_image(&self, image: Option<proto::Image>) -> Result<RgbImage32, EngineError> {
        let limits = search_limits(self.max_image_pixels);
        self.decode(move || image_from_proto(image, "image", limits))
            .await
    }

    /// A template image and its mask ([`template_from_proto`]), within the template side
    /// limits.
    async fn template_and_mask(
        &self,
        image: Option<proto::Image>,
        mask: Option<proto::Image>,
    ) -> Result<(RgbImage32, Option<TemplateMask>), EngineError> {
        self.decode(move || template_from_proto(image, mask, TEMPLATE_LIMITS))
            .await
    }

    /// Runs `decoding` on a blocking thread (a 40 MP PNG takes long enough to stall the
    /// runtime) once a decode permit is free.
    async fn decode<T: Send + 'static>(
        &self,
        decoding: impl FnOnce() -> Result<T, EngineError> + Send + 'static,
    ) -> Result<T, EngineError> {
        let _permit = self
            .permits
            .acquire()
            .await
            .map_err(|e| EngineError::Internal(format!("decode permits closed: {e}")))?;
        tokio::task::spawn_blocking(decoding)
            .await
            .map_err(|e| EngineError::Internal(format!("image decoding failed: {e}")))?
    }
}

impl Api {
    pub fn new(
        engine: Arc<OnceLock<Arc<Engine>>>,
        metrics: Metrics,
        decoder: ImageDecoder,
        match_defaults: MatchOptions,
    ) -> Self {
        Self {
            engine,
            metrics,
            decoder: Arc::new(decoder),
            match_defaults,
        }
    }

    fn engine(&self) -> Result<Arc<Engine>, Status> {
        self.engine
            .get()
            .cloned()
            .ok_or_else(|| Status::unavailable("the model is still loading; retry in a moment"))
    }

    /// Counts and times one finished RPC.
    fn record<T>(&self, rpc: &str, started: Instant, result: &Result<T, Status>) {
        let code = match result {
            Ok(_) => tonic::Code::Ok,
            Err(status) => status.code(),
        };
        self.metrics
            .requests
            .with_label_values(&[rpc, code_name(code)])
            .inc();
        self.metrics
            .latency_seconds
            .with_label_values(&[rpc])
            .observe(started.elapsed().as_secs_f64());
        if let Err(status) = result {
            // A Debug-formatted field: IDs quoted in the message cannot forge log lines.
            tracing::info!(
                rpc,
                code = code_name(code),
                error = status.message(),
                "request failed"
            );
        }
    }
}

pub(crate) fn code_name(code: tonic::Code) -> &'static str {
    use tonic::Code::*;
    match code {
        Ok => "OK",
        Cancelled => "CANCELLED",
        Unknown => "UNKNOWN",
        InvalidArgument => "INVALID_ARGUMENT",
        DeadlineExceeded => "DEADLINE_EXCEEDED",
        NotFound => "NOT_FOUND",
        AlreadyExists => "ALREADY_EXISTS",
        PermissionDenied => "PERMISSION_DENIED",
        ResourceExhausted => "RESOURCE_EXHAUSTED",
        FailedPrecondition => "FAILED_PRECONDITION",
        Aborted => "ABORTED",
        OutOfRange => "OUT_OF_RANGE",
        Unimplemented => "UNIMPLEMENTED",
        Internal => "INTERNAL",
        Unavailable => "UNAVAILABLE",
        DataLoss => "DATA_LOSS",
        Unauthenticated => "UNAUTHENTICATED",
    }
}

/// The templates a match request names: its `template_id`, or its `template_ids`, not both.
fn requested_templates(request: &proto::MatchRequest) -> Result<Vec<String>, EngineError> {
    match (request.template_id.is_empty(), request.template_ids.is_empty()) {
        (false, true) => Ok(vec![request.template_id.clone()]),
        (true, false) => Ok(request.template_ids.clone()),
        (true, true) => Err(EngineError::InvalidArgument(
            "template_id is empty; give the ID of a registered template (or several in template_ids)"
                .into(),
        )),
        (false, false) => Err(EngineError::InvalidArgument(
            "both template_id and template_ids are set; give one template_id, or all the templates in template_ids"
                .into(),
        )),
    }
}

/// One match, shared by `Match` and `MatchStream`.
async fn match_request(
    engine: &Engine,
    request: proto::MatchRequest,
    received: Instant,
    deadline: Option<Instant>,
    decoder: &ImageDecoder,
    defaults: &MatchOptions,
) -> Result<proto::MatchResponse, Status> {
    let work = async {
        let template_ids = requested_templates(&request)?;
        let RequestedMatch {
            options,
            roi,
            calibration_id,
        } = options_from_proto(request.options, defaults)?;
        // An unknown calibration is refused before the image is decoded.
        let calibration = match &calibration_id {
            Some(id) => Some(engine.calibration(id).await?.1),
            None => None,
        };
        // A full queue refuses before the image costs any memory.
        engine.admit_match()?;
        let image = decoder.search_image(request.image).await?;
        let (width, height) = (image.width, image.height);
        let decode_ms = received.elapsed().as_secs_f64() * 1e3;
        let answer_by = options.answer_by(received);
        let answers = engine
            .match_templates(&template_ids, image, options, roi, deadline, answer_by)
            .await?;
        // Several templates' searches ran side by side: the slowest one's times.
        let slowest = |f: &dyn Fn(&MatchAnswer) -> f64| answers.iter().map(f).fold(0.0, f64::max);
        let queue_ms = slowest(&|a| a.queue_ms);
        let network_ms = slowest(&|a| a.timings.prepare_ms + a.timings.network_ms);
        let postprocess_ms = slowest(&|a| a.timings.postprocess_ms());
        let mut poses: Vec<proto::Pose> = answers
            .iter()
            .zip(&template_ids)
            .flat_map(|(answer, id)| {
                answer
                    .poses
                    .iter()
                    .map(|pose| pose_to_proto(pose, id, &answer.template, calibration.as_ref()))
            })
            .collect();
        if answers.len() > 1 {
            poses.sort_by(|a, b| b.score.total_cmp(&a.score));
        }
        tracing::info!(
            templates = answers.len(),
            batch_size = answers.iter().map(|a| a.batch_size).max().unwrap_or(0),
            poses = poses.len(),
            queue_ms,
            network_ms,
            postprocess_ms,
            total_ms = received.elapsed().as_secs_f64() * 1e3,
            "matched"
        );
        Ok(proto::MatchResponse {
            request_id: request.request_id.clone(),
            template_id: request.template_id.clone(),
            template_ids: request.template_ids.clone(),
            timed_out: answers.iter().any(|a| a.timed_out),
            poses,
            world_unit: calibration
                .as_ref()
                .map(|c| c.unit().to_owned())
                .unwrap_or_default(),
            image_width: width,
            image_height: height,
            timings: Some(proto::Timings {
                decode_ms: decode_ms as f32,
                queue_ms: queue_ms as f32,
                network_ms: network_ms as f32,
                postprocess_ms: postprocess_ms as f32,
                total_ms: (received.elapsed().as_secs_f64() * 1e3) as f32,
            }),
        })
    };
    let result = match deadline {
        // Answer DEADLINE_EXCEEDED ourselves, a hair before the transport gives up on us.
        Some(deadline) => {
            let ours = deadline
                .checked_sub(std::time::Duration::from_millis(2))
                .unwrap_or(deadline);
            match tokio::time::timeout_at(ours.into(), work).await {
                Ok(result) => result,
                Err(_) => Err(EngineError::DeadlineExceeded(
                    "the request's deadline (grpc-timeout) passed before it was answered".into(),
                )),
            }
        }
        None => work.await,
    };
    result.map_err(status_of)
}

type MatchStreamOut = Pin<Box<dyn Stream<Item = Result<proto::MatchResponse, Status>> + Send>>;

#[tonic::async_trait]
impl PoseMatcher for Api {
    async fn register_template(
        &self,
        request: Request<proto::RegisterTemplateRequest>,
    ) -> Result<Response<proto::TemplateInfo>, Status> {
        let started = Instant::now();
        let request = request.into_inner();
        let span = tracing::info_span!("register_template", template_id = %request.template_id.escape_debug());
        let result = async {
            let engine = self.engine()?;
            let (image, mask) = self
                .decoder
                .template_and_mask(request.image, request.mask)
                .await
                .map_err(status_of)?;
            let origin = origin_from_proto(
                request.origin_x,
                request.origin_y,
                image.width,
                image.height,
            )
            .map_err(status_of)?;
            let labels = request.labels.into_iter().collect();
            let template = RegisteredTemplate {
                image,
                mask,
                origin,
            };
            engine
                .register(&request.template_id, template, request.replace, labels)
                .await
                .map(|meta| Response::new(template_info(meta)))
                .map_err(status_of)
        }
        .instrument(span)
        .await;
        self.record("RegisterTemplate", started, &result);
        result
    }

    async fn get_template(
        &self,
        request: Request<proto::GetTemplateRequest>,
    ) -> Result<Response<proto::TemplateInfo>, Status> {
        let started = Instant::now();
        let request = request.into_inner();
        let result = match self.engine() {
            Err(status) => Err(status),
            Ok(engine) if request.include_image => engine
                .get_with_image(&request.template_id)
                .await
                .map(|(meta, png, mask)| {
                    let encoded = |bytes| proto::Image {
                        data: Some(proto::image::Data::Encoded(bytes)),
                    };
                    Response::new(proto::TemplateInfo {
                        image: Some(encoded(png)),
                        mask: mask.map(|m| encoded(m.to_png())),
                        ..template_info(meta)
                    })
                })
                .map_err(status_of),
            Ok(engine) => engine
                .get(&request.template_id)
                .await
                .map(|meta| Response::new(template_info(meta)))
                .map_err(status_of),
        };
        self.record("GetTemplate", started, &result);
        result
    }

    async fn list_templates(
        &self,
        request: Request<proto::ListTemplatesRequest>,
    ) -> Result<Response<proto::ListTemplatesResponse>, Status> {
        let started = Instant::now();
        let request = request.into_inner();
        let result = match self.engine() {
            Err(status) => Err(status),
            Ok(engine) => engine
                .list(request.page_size as usize, &request.page_token)
                .await
                .map(|(page, next_page_token)| {
                    Response::new(proto::ListTemplatesResponse {
                        templates: page.into_iter().map(template_info).collect(),
                        next_page_token,
                    })
                })
                .map_err(status_of),
        };
        self.record("ListTemplates", started, &result);
        result
    }

    async fn delete_template(
        &self,
        request: Request<proto::DeleteTemplateRequest>,
    ) -> Result<Response<proto::DeleteTemplateResponse>, Status> {
        let started = Instant::now();
        let result = async {
            let engine = self.engine()?;
            engine
                .delete(&request.get_ref().template_id)
                .await
                .map(|deleted| Response::new(proto::DeleteTemplateResponse { deleted }))
                .map_err(status_of)
        }
        .await;
        self.record("DeleteTemplate", started, &result);
        result
    }

    async fn r#match(
        &self,
        request: Request<proto::MatchRequest>,
    ) -> Result<Response<proto::MatchResponse>, Status> {
        let received = Instant::now();
        let deadline = deadline_of(request.metadata(), received);
        let request = request.into_inner();
        let span = tracing::info_span!(
            "match",
            request_id = %request.request_id.escape_debug(),
            template_id = %request.template_id.escape_debug(),
        );
        let result = async {
            let engine = self.engine()?;
            match_request(
                &engine,
                request,
                received,
                deadline,
                &self.decoder,
                &self.match_defaults,
            )
            .await
        }
        .instrument(span.clone())
        .await
        .map(Response::new);
        span.in_scope(|| self.record("Match", received, &result));
        result
    }

    async fn register_calibration(
        &self,
        request: Request<proto::RegisterCalibrationRequest>,
    ) -> Result<Response<proto::CalibrationInfo>, Status> {
        let started = Instant::now();
        let request = request.into_inner();
        let result = async {
            let engine = self.engine()?;
            let spec = calibration_spec_from_proto(&request.points, &request.unit);
            engine
                .register_calibration(&request.calibration_id, spec, request.replace)
                .await
                .map(|(record, fitted)| Response::new(calibration_info(record, &fitted)))
                .map_err(status_of)
        }
        .await;
        self.record("RegisterCalibration", started, &result);
        result
    }

    async fn get_calibration(
        &self,
        request: Request<proto::GetCalibrationRequest>,
    ) -> Result<Response<proto::CalibrationInfo>, Status> {
        let started = Instant::now();
        let result = async {
            let engine = self.engine()?;
            engine
                .calibration(&request.get_ref().calibration_id)
                .await
                .map(|(record, fitted)| Response::new(calibration_info(record, &fitted)))
                .map_err(status_of)
        }
        .await;
        self.record("GetCalibration", started, &result);
        result
    }

    async fn list_calibrations(
        &self,
        request: Request<proto::ListCalibrationsRequest>,
    ) -> Result<Response<proto::ListCalibrationsResponse>, Status> {
        let started = Instant::now();
        let request = request.into_inner();
        let result = async {
            let engine = self.engine()?;
            let (page, next_page_token) = engine
                .list_calibrations(request.page_size as usize, &request.page_token)
                .await
                .map_err(status_of)?;
            let calibrations = page
                .into_iter()
                .map(|record| {
                    // Stored calibrations were fitted when registered; one that no longer fits
                    // is reported with what is stored and no model.
                    match crate::world::WorldCalibration::fit(record.spec.clone()) {
                        Ok(fitted) => calibration_info(record, &fitted),
                        Err(_) => proto::CalibrationInfo {
                            calibration_id: record.calibration_id,
                            unit: record.spec.unit,
                            ..Default::default()
                        },
                    }
                })
                .collect();
            Ok(Response::new(proto::ListCalibrationsResponse {
                calibrations,
                next_page_token,
            }))
        }
        .await;
        self.record("ListCalibrations", started, &result);
        result
    }

    async fn delete_calibration(
        &self,
        request: Request<proto::DeleteCalibrationRequest>,
    ) -> Result<Response<proto::DeleteCalibrationResponse>, Status> {
        let started = Instant::now();
        let result = async {
            let engine = self.engine()?;
            engine
                .delete_calibration(&request.get_ref().calibration_id)
                .await
                .map(|deleted| Response::new(proto::DeleteCalibrationResponse { deleted }))
                .map_err(status_of)
        }
        .await;
        self.record("DeleteCalibration", started, &result);
        result
    }

    type MatchStreamStream = MatchStreamOut;

    /// Requests of one stream are answered in order, one at a time; an invalid request ends the
    /// stream with its status (the message names its request_id) so a line never silently
    /// skips a frame.
    async fn match_stream(
        &self,
        request: Request<Streaming<proto::MatchRequest>>,
    ) -> Result<Response<Self::MatchStreamStream>, Status> {
        let engine = self.engine()?;
        let mut inbound = request.into_inner();
        let (sender, receiver) = mpsc::channel(16);
        let metrics = self.metrics.clone();
        let counter = Api {
            engine: self.engine.clone(),
            metrics,
            decoder: self.decoder.clone(),
            match_defaults: self.match_defaults.clone(),
        };
        tokio::spawn(async move {
            let mut frame = 0usize;
            while let Some(next) = inbound.next().await {
                frame += 1;
                let request = match next {
                    Ok(request) => request,
                    Err(status) => {
                        // A frame the transport could not take (too large, malformed): the
                        // client hears why and which frame, instead of a stream that ends OK.
                        tracing::debug!(%status, frame, "match stream input failed");
                        let hint = if status.code() == tonic::Code::OutOfRange
                            || status.message().contains("too large")
                        {
                            "; send smaller frames or raise max_message_bytes"
                        } else {
                            ""
                        };
                        let status = Status::new(
                            status.code(),
                            format!("frame {frame}: {}{hint}", status.message()),
                        );
                        counter.record(
                            "MatchStream",
                            Instant::now(),
                            &Err::<(), _>(status.clone()),
                        );
                        let _ = sender.send(Err(status)).await;
                        break;
                    }
                };
                let received = Instant::now();
                let request_id = request.request_id.clone();
                let span = tracing::info_span!(
                    "match_stream",
                    request_id = %request.request_id.escape_debug(),
                    template_id = %request.template_id.escape_debug(),
                    batch_size = tracing::field::Empty,
                    poses = tracing::field::Empty,
                );
                let defaults = &counter.match_defaults;
                let decoder = &counter.decoder;
                let result = match_request(&engine, request, received, None, decoder, defaults)
                    .instrument(span)
                    .await
                    .map_err(|s| {
                        Status::new(
                            s.code(),
                            format!("request_id {}: {}", quoted(&request_id), s.message()),
                        )
                    });
                counter.record("MatchStream", received, &result);
                let failed = result.is_err();
                if sender.send(result).await.is_err() || failed {
                    break;
                }
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(receiver))))
    }
}
