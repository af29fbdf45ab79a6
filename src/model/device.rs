//! Backend selection at run time. burn panics on an unknown `BURN_DEVICE`; a factory operator
//! deserves an error that lists what this binary was built with.

use burn::prelude::Device;

#[derive(Debug, thiserror::Error)]
#[error(
    "BURN_DEVICE={requested} is not available in this build; choose one of: {available} (rebuild with `--features ndarray` for ndarray)"
)]
pub struct DeviceError {
    requested: String,
    available: String,
}

/// Backends compiled into this binary, in preference order.
pub fn available_backends() -> Vec<&'static str> {
    let mut names = Vec::new();
    if cfg!(feature = "flex") {
        names.push("flex");
    }
    if cfg!(feature = "ndarray") {
        names.push("ndarray");
    }
    names
}

/// The device named by `BURN_DEVICE` (case-insensitive), or the first compiled backend.
pub fn select_device() -> Result<Device, DeviceError> {
    match std::env::var("BURN_DEVICE") {
        Ok(name) if !name.trim().is_empty() => device_by_name(&name),
        _ => device_by_name(available_backends().first().copied().unwrap_or("none")),
    }
}

fn device_by_name(name: &str) -> Result<Device, DeviceError> {
    match name.trim().to_ascii_lowercase().as_str() {
        #[cfg(feature = "flex")]
        "flex" => Ok(Device::flex()),
        #[cfg(feature = "ndarray")]
        "ndarray" => Ok(Device::ndarray()),
        _ => Err(DeviceError {
            requested: name.to_owned(),
            available: available_backends().join(", "),
        }),
    }
}

/// Whether tensors on `device` live in host memory without autodiff, so that the host CPU
/// inference code ([`super::InferenceNetwork::host`]) may read and write them directly.
pub fn is_host_cpu(device: &Device) -> bool {
    if device.is_autodiff() {
        return false;
    }
    #[cfg(feature = "flex")]
    if *device == Device::flex() {
        return true;
    }
    #[cfg(feature = "ndarray")]
    if *device == Device::ndarray() {
        return true;
    }
    false
}
