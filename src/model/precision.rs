//! The arithmetic of the network's matrix products, chosen by the operator.
//!
//! `f32` is the exact function of the checkpoint (the parity fixtures hold it to 1e-4).
//! `bf16` rounds both operands of every large product (backbone pointwise layers, upsampler and
//! head convolutions) to bfloat16 and runs them on AMX tiles or with AVX-512 BF16 dot products
//! (see `bf16.rs`), accumulating in f32: several times faster, slightly different numbers (README
//! "Speed" shows the held-out accuracy of both). Everything else (depthwise convolutions,
//! normalisations, activations, correlation, peak reading, refinement) stays f32 in both. `auto` —
//! what the CLI and the service use unless told otherwise — is bf16 where the CPU has either and
//! the network runs on the CPU implementation, f32 elsewhere: on held-out pairs the two agree
//! within noise (docs/speed.md), and bf16 halves a large frame's time. `f32` pins the exact
//! function everywhere.

use std::fmt;
use std::str::FromStr;

use super::cpu::bf16;

/// Written `f32`, `bf16` or `auto` in flags and settings; this is the one parser of those
/// words. The library's networks run f32 unless given another precision.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize, serde::Serialize)]
#[serde(try_from = "String", into = "String")]
pub enum Precision {
    #[default]
    F32,
    Bf16,
    /// [`Precision::Bf16`] where it can run, [`Precision::F32`] elsewhere
    /// ([`Precision::resolve`]).
    Auto,
}

impl FromStr for Precision {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "f32" => Ok(Self::F32),
            "bf16" => Ok(Self::Bf16),
            "auto" => Ok(Self::Auto),
            other => Err(format!(
                "unknown precision `{other}`: use \"f32\" (exact), \"bf16\" (AMX tiles or AVX-512 BF16) or \"auto\" (bf16 where the CPU has either, else f32)"
            )),
        }
    }
}

impl fmt::Display for Precision {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::F32 => "f32",
            Self::Bf16 => "bf16",
            Self::Auto => "auto",
        })
    }
}

impl From<Precision> for String {
    fn from(precision: Precision) -> Self {
        precision.to_string()
    }
}

impl TryFrom<String> for Precision {
    type Error = String;

    fn try_from(s: String) -> Result<Self, String> {
        s.parse()
    }
}

/// Why a precision cannot run here.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PrecisionError {
    #[error(
        "precision bf16 needs AVX-512 BF16 (AMD Zen 4, Intel Cooper Lake or newer) or Intel AMX tiles (Sapphire Rapids or newer, Linux 5.16 or newer), which this machine does not offer: use precision f32"
    )]
    NoBf16Instructions,
    #[error(
        "precision bf16 runs on the CPU implementation only (BURN_DEVICE flex or ndarray): use precision f32 on this device"
    )]
    NotHostCpu,
}

impl Precision {
    /// Whether this machine can run `self` at all (the device is checked where the network is
    /// built).
    pub fn check_machine(self) -> Result<(), PrecisionError> {
        match self {
            Self::F32 | Self::Auto => Ok(()),
            Self::Bf16 if bf16::available() => Ok(()),
            Self::Bf16 => Err(PrecisionError::NoBf16Instructions),
        }
    }
}

impl Precision {
    /// The precision a network runs: `auto` becomes bf16 where this machine has bf16 instructions and
    /// the network runs on the CPU implementation (`host_kernels`), f32 elsewhere; the others
    /// stay as they are.
    pub fn resolve(self, host_kernels: bool) -> Precision {
        match self {
            Self::Auto if host_kernels && bf16::available() => Self::Bf16,
            Self::Auto => Self::F32,
            other => other,
        }
    }

    /// What runs the products at this precision on this machine, for logs and benchmarks:
    /// `f32`, `bf16 (AMX tiles)`, `bf16 (AVX-512 BF16)` (`auto` as it is, unresolved).
    pub fn arithmetic(self) -> String {
        match (self, bf16::instructions()) {
            (Self::Bf16, Some(instructions)) => format!("bf16 ({instructions})"),
            (other, _) => other.to_string(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn words_parse_and_print_back() {
        for precision in [Precision::F32, Precision::Bf16, Precision::Auto] {
            assert_eq!(precision.to_string().parse::<Precision>(), Ok(precision));
        }
        assert_eq!(" BF16 ".parse::<Precision>(), Ok(Precision::Bf16));
        let error = "fp16".parse::<Precision>().unwrap_err();
        assert!(error.contains("fp16") && error.contains("bf16"), "{error}");
    }

    #[test]
    fn auto_is_bf16_exactly_where_bf16_instructions_and_the_cpu_implementation_are() {
        let expected = if bf16::available() {
            Precision::Bf16
        } else {
            Precision::F32
        };
        assert_eq!(Precision::Auto.resolve(true), expected);
        assert_eq!(Precision::Auto.resolve(false), Precision::F32);
        assert_eq!(Precision::Auto.check_machine(), Ok(()));
        assert_eq!(Precision::F32.resolve(true), Precision::F32);
        assert_eq!(Precision::Bf16.resolve(false), Precision::Bf16);
    }

    #[test]
    fn bf16_is_refused_exactly_where_there_are_no_bf16_instructions() {
        assert_eq!(Precision::F32.check_machine(), Ok(()));
        let bf16 = Precision::Bf16.check_machine();
        if bf16::available() {
            assert_eq!(bf16, Ok(()));
        } else {
            let message = bf16.unwrap_err().to_string();
            assert!(
                message.contains("AVX-512 BF16") && message.contains("f32"),
                "{message}"
            );
        }
    }
}
