//! gRPC status → HTTP status, and the JSON error body every failed HTTP call carries:
//! `{"code": "NOT_FOUND", "message": "..."}`, `code` being the gRPC code's name so that one
//! vocabulary serves both transports.

use axum::Json;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use tonic::{Code, Status};

use crate::grpc::api::code_name;

/// The HTTP status of a gRPC code (the mapping of Google's API design guide, as grpc-gateway
/// and Envoy's transcoder use it).
pub fn http_status(code: Code) -> StatusCode {
    match code {
        Code::Ok => StatusCode::OK,
        Code::InvalidArgument | Code::FailedPrecondition | Code::OutOfRange => {
            StatusCode::BAD_REQUEST
        }
        Code::Unauthenticated => StatusCode::UNAUTHORIZED,
        Code::PermissionDenied => StatusCode::FORBIDDEN,
        Code::NotFound => StatusCode::NOT_FOUND,
        Code::AlreadyExists | Code::Aborted => StatusCode::CONFLICT,
        Code::ResourceExhausted => StatusCode::TOO_MANY_REQUESTS,
        Code::Cancelled => StatusCode::from_u16(499).expect("499 is a valid status"),
        Code::Unimplemented => StatusCode::NOT_IMPLEMENTED,
        Code::Unavailable => StatusCode::SERVICE_UNAVAILABLE,
        Code::DeadlineExceeded => StatusCode::GATEWAY_TIMEOUT,
        Code::Internal | Code::Unknown | Code::DataLoss => StatusCode::INTERNAL_SERVER_ERROR,
    }
}

/// A refused call: its HTTP status and the JSON error body.
#[derive(Debug, Serialize)]
pub struct ErrorBody {
    #[serde(skip)]
    status: StatusCode,
    code: &'static str,
    message: String,
    /// Answer with `WWW-Authenticate: Bearer` (a missing or wrong token).
    #[serde(skip)]
    bearer_challenge: bool,
}

impl ErrorBody {
    pub fn new(status: StatusCode, code: &'static str, message: &str) -> Self {
        Self {
            status,
            code,
            message: message.to_owned(),
            bearer_challenge: false,
        }
    }

    /// The answer to a call the service refused with `status`.
    pub fn from_status(status: &Status) -> Self {
        Self {
            bearer_challenge: status.code() == Code::Unauthenticated,
            ..Self::new(
                http_status(status.code()),
                code_name(status.code()),
                status.message(),
            )
        }
    }
}

impl IntoResponse for ErrorBody {
    fn into_response(self) -> Response {
        let (status, challenge) = (self.status, self.bearer_challenge);
        let mut response = Json(self).into_response();
        *response.status_mut() = status;
        response.headers_mut().insert(
            axum::http::header::X_CONTENT_TYPE_OPTIONS,
            axum::http::HeaderValue::from_static("nosniff"),
        );
        if challenge {
            response.headers_mut().insert(
                axum::http::header::WWW_AUTHENTICATE,
                axum::http::HeaderValue::from_static("Bearer"),
            );
        }
        response
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_codes_the_service_answers_map_to_their_http_statuses() {
        for (code, http) in [
            (Code::InvalidArgument, 400),
            (Code::Unauthenticated, 401),
            (Code::NotFound, 404),
            (Code::AlreadyExists, 409),
            (Code::ResourceExhausted, 429),
            (Code::Unavailable, 503),
            (Code::DeadlineExceeded, 504),
            (Code::Internal, 500),
        ] {
            assert_eq!(http_status(code).as_u16(), http, "{code:?}");
        }
    }
}
