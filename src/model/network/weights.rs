//! Getting weights into a [`Tdcm`]: the authors' PyTorch checkpoint (`.pth`, or the same tensors
//! as `.safetensors`) through an explicit key map, and our own format (burnpack, `.bpk`).
//!
//! # Checkpoint names → our module paths
//!
//! | PyTorch (official `model.pth`)                | PoseMatch `Tdcm`                                  |
//! | --------------------------------------------- | ------------------------------------------------- |
//! | `backbone_T.`                                 | `template_encoder.backbone.`                      |
//! | `backbone_O.`                                 | `search_matcher.backbone.`                        |
//! | `….stem.0.{weight,bias}`                      | `….stem_conv.{weight,bias}`                       |
//! | `….stem.1.{weight,bias}` (LayerNorm)          | `….stem_norm.{gamma,beta}`                        |
//! | `….stage1.blocks.N.conv_dw/norm`              | `….blocks.N.conv_dw/norm`                         |
//! | `….stage1.blocks.N.mlp.{fc1,grn,fc2}`         | `….blocks.N.{fc1,grn,fc2}`                        |
//! | `….norm.*` (BatchNorm)                        | `….norm.{gamma,beta,running_mean,running_var}`    |
//! | `pointwise_conv.` (a 3x3 conv)                | `search_matcher.fusion.`                          |
//! | `conv1.`, `bn1.`, `conv2.`, `bn2.`            | `search_matcher.decoder.{conv1,bn1,conv2,bn2}.`   |
//! | `conv_{score,sign,cos,scale_x,scale_y}.0.`    | `search_matcher.heads.{…}.conv3x3.`               |
//! | `conv_{score,sign,cos,scale_x,scale_y}.2.`    | `search_matcher.heads.{…}.conv1x1.`               |
//!
//! burn-store's `PyTorchToBurnAdapter` then transposes Linear weights (`[out, in]` → `[in, out]`)
//! and renames norm `weight`/`bias` to `gamma`/`beta`. The four `num_batches_tracked` counters
//! are training bookkeeping and are ignored. Anything else missing, unused or misshapen is a
//! [`LoadError`] that names the first offending tensor.

use std::path::{Path, PathBuf};

use burn::prelude::*;
use burn::store::{
    ApplyError, ApplyResult, BurnpackStore, KeyRemapper, ModuleSnapshot, PytorchStore,
    SafetensorsStore,
};

use super::tdcm::{Tdcm, TdcmConfig};
use super::trained_on::{METADATA_KEY, TrainedOn};

/// Regex rewrites from checkpoint names to ours, applied in order (see the module docs).
pub const PYTORCH_KEY_MAP: &[(&str, &str)] = &[
    (r"^backbone_T\.", "template_encoder.backbone."),
    (r"^backbone_O\.", "search_matcher.backbone."),
    (r"\.stem\.0\.", ".stem_conv."),
    (r"\.stem\.1\.", ".stem_norm."),
    (r"\.stage1\.blocks\.", ".blocks."),
    (r"\.mlp\.(fc1|grn|fc2)\.", ".$1."),
    (r"^pointwise_conv\.", "search_matcher.fusion."),
    (r"^(conv1|bn1|conv2|bn2)\.", "search_matcher.decoder.$1."),
    (
        r"^conv_(score|sign|cos|scale_x|scale_y)\.0\.",
        "search_matcher.heads.$1.conv3x3.",
    ),
    (
        r"^conv_(score|sign|cos|scale_x|scale_y)\.2\.",
        "search_matcher.heads.$1.conv1x1.",
    ),
];

/// Why weights could not be loaded. Every variant says which file and, where it applies, which
/// tensor.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error("weights file {path}: {message}")]
    Unreadable { path: PathBuf, message: String },
    #[error("weights {source_name} do not fit the TDCM architecture: tensor `{tensor}`: {problem}")]
    Mismatch {
        source_name: String,
        tensor: String,
        problem: String,
    },
    #[error("weights {source_name}: its training record ({METADATA_KEY}) is unreadable: {problem}")]
    TrainedOn {
        source_name: String,
        problem: String,
    },
    #[error(
        "weights file {path} is neither a PyTorch checkpoint, safetensors nor burnpack (by its extension or its first bytes); give a .pth/.pt, .safetensors or .bpk file"
    )]
    UnknownFormat { path: PathBuf },
}

/// On-disk formats we read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WeightsFormat {
    /// A PyTorch `state_dict` of the official model, names as in the authors' repository.
    Pytorch,
    /// The same tensors and names as a PyTorch checkpoint, in safetensors.
    PytorchSafetensors,
    /// Our own format: burnpack with our module paths.
    Burnpack,
}

impl WeightsFormat {
    /// The format of the file at `path`: by its extension, or else by its first bytes. A
    /// mounted file often loses its name (a container's `/models/weights`, a Kubernetes secret
    /// key), and the three formats are told apart by their headers.
    pub fn of_file(path: &Path) -> Result<Self, LoadError> {
        if let Some(format) = Self::from_extension(path) {
            return Ok(format);
        }
        use std::io::Read;
        let mut head = Vec::with_capacity(9);
        std::fs::File::open(path)
            .and_then(|file| file.take(9).read_to_end(&mut head))
            .map_err(|e| LoadError::Unreadable {
                path: path.to_owned(),
                message: e.to_string(),
            })?;
        Self::from_header(&head).ok_or_else(|| LoadError::UnknownFormat {
            path: path.to_owned(),
        })
    }

    fn from_extension(path: &Path) -> Option<Self> {
        match path.extension().and_then(|e| e.to_str()) {
            Some("pth" | "pt") => Some(Self::Pytorch),
            Some("safetensors") => Some(Self::PytorchSafetensors),
            Some("bpk") => Some(Self::Burnpack),
            _ => None,
        }
    }

    /// Burnpack starts with `NRUB` (`BURN` as a little-endian u32); a PyTorch checkpoint is a
    /// zip archive (`PK\x03\x04`, since PyTorch 1.6) or a bare pickle (protocol byte `0x80`);
    /// safetensors is a little-endian u64 header length followed by the header's JSON `{`.
    fn from_header(head: &[u8]) -> Option<Self> {
        match head {
            [b'N', b'R', b'U', b'B', ..] => Some(Self::Burnpack),
            [b'P', b'K', 3, 4, ..] | [0x80, 2..=5, ..] => Some(Self::Pytorch),
            [length @ .., b'{'] if length.len() == 8 => Some(Self::PytorchSafetensors),
            _ => None,
        }
    }
}

fn key_remapper() -> KeyRemapper {
    KeyRemapper::from_patterns(PYTORCH_KEY_MAP.to_vec()).expect("static key map is valid regex")
}

/// PoseMatch's own default weights, compiled into the binary so that a fresh machine needs no
/// checkpoint from anywhere else. Trained from random initialisation by PoseMatch's own code;
/// provenance and measured accuracy in `models/README.md`.
/// The bytes are 64-byte aligned: burnpack tensors are read in place as `f32`.
pub const DEFAULT_WEIGHTS: &[u8] = &EMBEDDED.0;

/// How messages name [`DEFAULT_WEIGHTS`].
pub const DEFAULT_WEIGHTS_NAME: &str = "embedded default weights";

#[repr(C, align(64))]
struct Aligned<Bytes: ?Sized>(Bytes);

static EMBEDDED: &Aligned<[u8]> =
    &Aligned(*include_bytes!("../../../models/posematch-default.bpk"));

/// Which weights a model runs: the one type the CLI, the service settings and training use.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum WeightsSource {
    /// [`DEFAULT_WEIGHTS`], compiled into the binary.
    Embedded,
    /// A weights file: `.bpk` (PoseMatch), `.pth`/`.pt` or `.safetensors` (official layout).
    File(PathBuf),
}

impl WeightsSource {
    /// A `--weights` flag or a `weights` setting: absent or empty means the embedded default;
    /// so does the word `default` (as in `posematch train --init default`).
    pub fn from_path(path: Option<&Path>) -> Self {
        match path {
            Some(p) if !p.as_os_str().is_empty() && p.as_os_str() != "default" => {
                Self::File(p.to_owned())
            }
            _ => Self::Embedded,
        }
    }

    /// Builds the network on `device` with these weights.
    pub fn load(&self, device: &Device) -> Result<Tdcm, LoadError> {
        match self {
            Self::Embedded => {
                load_weights_from_bytes(DEFAULT_WEIGHTS, DEFAULT_WEIGHTS_NAME, device)
            }
            Self::File(path) => load_weights(path, device),
        }
    }

    /// What these weights were trained on, where the file records it (our own format since
    /// issue 39); `None` for the official formats and older files.
    pub fn trained_on(&self) -> Result<Option<TrainedOn>, LoadError> {
        match self {
            Self::Embedded => trained_on_in(
                burn::store::burn_pack::Reader::from_bytes(
                    burn::store::burn_pack::Bytes::from_bytes_vec(DEFAULT_WEIGHTS.to_vec()),
                ),
                DEFAULT_WEIGHTS_NAME,
            ),
            Self::File(path) => match WeightsFormat::of_file(path)? {
                WeightsFormat::Burnpack => trained_on_in(
                    burn::store::burn_pack::Reader::from_file_exact(path),
                    &path.display().to_string(),
                ),
                WeightsFormat::Pytorch | WeightsFormat::PytorchSafetensors => Ok(None),
            },
        }
    }
}

/// The record in a burnpack's metadata, if it has one.
fn trained_on_in(
    reader: Result<burn::store::burn_pack::Reader, burn::store::burn_pack::Error>,
    source_name: &str,
) -> Result<Option<TrainedOn>, LoadError> {
    let problem = |problem: String| LoadError::TrainedOn {
        source_name: source_name.to_owned(),
        problem,
    };
    let reader = reader.map_err(|e| problem(e.to_string()))?;
    reader
        .metadata()
        .get(METADATA_KEY)
        .map(|json| TrainedOn::from_json(json).map_err(|e| problem(e.to_string())))
        .transpose()
}

impl std::fmt::Display for WeightsSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Embedded => f.write_str(DEFAULT_WEIGHTS_NAME),
            Self::File(path) => write!(f, "{}", path.display()),
        }
    }
}

/// Builds the network on `device` and loads the weights at `path` ([`WeightsFormat::of_file`]).
pub fn load_weights(path: &Path, device: &Device) -> Result<Tdcm, LoadError> {
    let mut model = TdcmConfig::new().init(device);
    let unreadable = |message: String| LoadError::Unreadable {
        path: path.to_owned(),
        message,
    };
    if !path.is_file() {
        return Err(unreadable("no such file".into()));
    }
    let result = match WeightsFormat::of_file(path)? {
        WeightsFormat::Pytorch => {
            let mut store = PytorchStore::from_file(path)
                .remap(key_remapper())
                .allow_partial(true)
                .validate(false);
            model
                .load_from(&mut store)
                .map_err(|e| unreadable(e.to_string()))?
        }
        WeightsFormat::PytorchSafetensors => {
            let mut store = SafetensorsStore::from_file(path)
                .remap(key_remapper())
                .with_from_adapter(burn::store::PyTorchToBurnAdapter)
                .allow_partial(true)
                .validate(false);
            model
                .load_from(&mut store)
                .map_err(|e| unreadable(e.to_string()))?
        }
        WeightsFormat::Burnpack => {
            let mut store = BurnpackStore::from_file(path)
                .auto_extension(false)
                .allow_partial(true)
                .validate(false);
            model
                .load_from(&mut store)
                .map_err(|e| unreadable(e.to_string()))?
        }
    };
    check_complete(&result, &path.display().to_string())?;
    Ok(model)
}

/// Loads our own format from bytes (the embedded default weights).
pub fn load_weights_from_bytes(
    bytes: &'static [u8],
    source_name: &str,
    device: &Device,
) -> Result<Tdcm, LoadError> {
    let mut model = TdcmConfig::new().init(device);
    let mut store = BurnpackStore::from_static(bytes)
        .allow_partial(true)
        .validate(false);
    let result = model
        .load_from(&mut store)
        .map_err(|e| LoadError::Unreadable {
            path: source_name.into(),
            message: e.to_string(),
        })?;
    check_complete(&result, source_name)?;
    Ok(model)
}

/// Saves in our own format (burnpack), with what the weights were trained on where that is
/// known ([`TrainedOn`], in the file's metadata). Overwrites `path`.
pub fn save_weights(
    model: &Tdcm,
    trained_on: Option<&TrainedOn>,
    path: &Path,
) -> Result<(), LoadError> {
    let mut store = BurnpackStore::from_file(path)
        .auto_extension(false)
        .overwrite(true)
        .metadata("format", "posematch-tdcm")
        .metadata("license_note", "see models/README.md for provenance");
    if let Some(record) = trained_on {
        store = store.metadata(METADATA_KEY, record.to_json());
    }
    model
        .save_into(&mut store)
        .map_err(|e| LoadError::Unreadable {
            path: path.to_owned(),
            message: e.to_string(),
        })
}

/// Our module paths → checkpoint names: the inverse of [`PYTORCH_KEY_MAP`], applied in order
/// (a block's `conv_dw`/`norm` before its `mlp` layers, which the first rule must not touch).
pub const PYTORCH_EXPORT_KEY_MAP: &[(&str, &str)] = &[
    (r"^template_encoder\.backbone\.", "backbone_T."),
    (r"^search_matcher\.backbone\.", "backbone_O."),
    (r"\.stem_conv\.", ".stem.0."),
    (r"\.stem_norm\.", ".stem.1."),
    (
        r"\.blocks\.(\d+)\.(conv_dw|norm)\.",
        ".stage1.blocks.$1.$2.",
    ),
    (
        r"\.blocks\.(\d+)\.(fc1|grn|fc2)\.",
        ".stage1.blocks.$1.mlp.$2.",
    ),
    (r"^search_matcher\.fusion\.", "pointwise_conv."),
    (r"^search_matcher\.decoder\.(conv1|bn1|conv2|bn2)\.", "$1."),
    (
        r"^search_matcher\.heads\.(score|sign|cos|scale_x|scale_y)\.conv3x3\.",
        "conv_$1.0.",
    ),
    (
        r"^search_matcher\.heads\.(score|sign|cos|scale_x|scale_y)\.conv1x1\.",
        "conv_$1.2.",
    ),
];

/// Writes `model` as a safetensors file with the official checkpoint's names and layouts (Linear
/// weights `[out, in]`, norms' `weight`/`bias`): what `training/train.py --init-weights` starts
/// from, so a GPU run can continue our own weights. `load_weights` reads it back unchanged.
/// Overwrites `path`.
pub fn export_pytorch_safetensors(model: &Tdcm, path: &Path) -> Result<(), LoadError> {
    let remapper = KeyRemapper::from_patterns(PYTORCH_EXPORT_KEY_MAP.to_vec())
        .expect("static key map is valid regex");
    let mut store = SafetensorsStore::from_file(path)
        .overwrite(true)
        .remap(remapper)
        .with_to_adapter(burn::store::BurnToPyTorchAdapter)
        .metadata("format", "tdcm-official-names");
    model
        .save_into(&mut store)
        .map_err(|e| LoadError::Unreadable {
            path: path.to_owned(),
            message: e.to_string(),
        })
}

/// Turns burn-store's report into a hard error on the first problem, so that a wrong checkpoint
/// never runs with half-random weights.
fn check_complete(result: &ApplyResult, source_name: &str) -> Result<(), LoadError> {
    let mismatch = |tensor: &str, problem: String| LoadError::Mismatch {
        source_name: source_name.to_owned(),
        tensor: tensor.to_owned(),
        problem,
    };
    if let Some(error) = result.errors.first() {
        return Err(match error {
            ApplyError::ShapeMismatch {
                path,
                expected,
                found,
            } => mismatch(
                path,
                format!("expected shape {:?}, the file has {:?}", expected, found),
            ),
            ApplyError::DTypeMismatch {
                path,
                expected,
                found,
            } => mismatch(
                path,
                format!("expected {expected:?}, the file has {found:?}"),
            ),
            ApplyError::AdapterError { path, message }
            | ApplyError::LoadError { path, message } => mismatch(path, message.clone()),
        });
    }
    if let Some((path, _)) = result.missing.first() {
        return Err(mismatch(path, "missing from the file".into()));
    }
    if let Some(path) = result
        .unused
        .iter()
        .find(|p| !p.ends_with("num_batches_tracked"))
    {
        return Err(mismatch(
            path,
            "the file has this tensor but the network has no such parameter".into(),
        ));
    }
    Ok(())
}
