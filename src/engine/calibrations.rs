//! Calibrations as named resources ([`crate::world`]): registered, listed and deleted like
//! templates, kept in the same store, and looked up by ID when a match asks for world units.
//! Only the points and unit are stored; the map is fitted again from them when used (a few
//! microseconds), so what is stored is exactly what the client sent.

use super::registry::{check_id, into_page, page_after, page_size};
use super::store::{CalibrationRecord, PutOutcome};
use super::{Engine, EngineError};
use crate::world::{CalibrationSpec, WorldCalibration};

impl Engine {
    /// Fits `spec` (refusing points that do not determine a map) and stores it under
    /// `calibration_id`. The same points and unit again is a no-op; other ones need `replace`.
    pub async fn register_calibration(
        &self,
        calibration_id: &str,
        spec: CalibrationSpec,
        replace: bool,
    ) -> Result<(CalibrationRecord, WorldCalibration), EngineError> {
        check_id("calibration_id", calibration_id)?;
        if calibration_id.is_empty() {
            return Err(EngineError::InvalidArgument(
                "calibration_id is empty; name the calibration (e.g. line-3-camera-1)".into(),
            ));
        }
        let fitted = WorldCalibration::fit(spec)
            .map_err(|e| EngineError::InvalidArgument(format!("calibration: {e}")))?;
        match self
            .store
            .put_calibration(calibration_id, fitted.spec().clone(), replace)
            .await?
        {
            PutOutcome::Unchanged(record) | PutOutcome::Written { meta: record, .. } => {
                Ok((record, fitted))
            }
            PutOutcome::Conflict(_) => {
                Err(EngineError::CalibrationExists(calibration_id.to_owned()))
            }
        }
    }

    /// A registered calibration, fitted.
    pub async fn calibration(
        &self,
        calibration_id: &str,
    ) -> Result<(CalibrationRecord, WorldCalibration), EngineError> {
        let not_found = || EngineError::CalibrationNotFound(calibration_id.to_owned());
        if check_id("calibration_id", calibration_id).is_err() || calibration_id.is_empty() {
            return Err(not_found());
        }
        let record = self
            .store
            .get_calibration(calibration_id)
            .await?
            .ok_or_else(not_found)?;
        let fitted = WorldCalibration::fit(record.spec.clone()).map_err(|e| {
            EngineError::Store(super::store::StoreError::Corrupt {
                origin: format!("calibration {}", super::quoted(calibration_id)),
                message: e.to_string(),
            })
        })?;
        Ok((record, fitted))
    }

    /// One page of calibrations in ID order; the token is where the next page starts.
    pub async fn list_calibrations(
        &self,
        page_size_asked: usize,
        page_token: &str,
    ) -> Result<(Vec<CalibrationRecord>, String), EngineError> {
        let size = page_size(page_size_asked)?;
        let after = page_after(page_token)?;
        let page = self
            .store
            .list_calibrations(after.as_deref(), size + 1)
            .await?;
        Ok(into_page(page, size, |record| &record.calibration_id))
    }

    /// `false` when it was not registered.
    pub async fn delete_calibration(&self, calibration_id: &str) -> Result<bool, EngineError> {
        if check_id("calibration_id", calibration_id).is_err() {
            return Ok(false);
        }
        Ok(self.store.remove_calibration(calibration_id).await?)
    }
}
