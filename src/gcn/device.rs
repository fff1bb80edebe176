//! Which device SR-GCN training and inference compute on: the Flex CPU backend (the default,
//! and the only one in a build without GPU features) or, with the `gpu` cargo feature, a GPU
//! through burn's wgpu runtime (Vulkan, Metal or DX12; `vulkan` adds SPIR-V shaders). The choice is made once per process (`librplus --device ...`) and read by every
//! SR-GCN entry point through [`compute`]; LIBR, wICP and the FEM stay on the CPU.

use super::GcnError;
use burn::tensor::Device;
use std::str::FromStr;
use std::sync::RwLock;

/// A compute device for the SR-GCN.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ComputeDevice {
    /// The Flex CPU backend (rayon threads).
    #[default]
    Cpu,
    /// A GPU through wgpu (needs the `gpu` feature): the one wgpu prefers (a high-power GPU,
    /// or `CUBECL_WGPU_DEFAULT_DEVICE`), or the discrete GPU with this index.
    Gpu(Option<usize>),
}

impl FromStr for ComputeDevice {
    type Err = GcnError;

    /// `cpu`, `gpu` (the GPU wgpu prefers) or `gpu:N` (the N-th discrete GPU).
    fn from_str(s: &str) -> Result<Self, GcnError> {
        let s = s.trim();
        if s.eq_ignore_ascii_case("cpu") {
            return Ok(Self::Cpu);
        }
        let lower = s.to_ascii_lowercase();
        let bad = || GcnError::Device(format!("device {s:?}: expected cpu, gpu or gpu:N"));
        match lower.strip_prefix("gpu") {
            Some("") => Ok(Self::Gpu(None)),
            Some(rest) => rest
                .strip_prefix(':')
                .and_then(|n| n.parse::<usize>().ok())
                .map(|n| Self::Gpu(Some(n)))
                .ok_or_else(bad),
            None => Err(bad()),
        }
    }
}

impl std::fmt::Display for ComputeDevice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Cpu => write!(f, "cpu"),
            Self::Gpu(None) => write!(f, "gpu"),
            Self::Gpu(Some(i)) => write!(f, "gpu:{i}"),
        }
    }
}

impl ComputeDevice {
    /// The burn device, or an error naming the missing feature.
    pub fn burn(self) -> Result<Device, GcnError> {
        match self {
            Self::Cpu => Ok(Device::flex()),
            #[cfg(feature = "gpu")]
            Self::Gpu(i) => Ok(Device::wgpu(match i {
                None => burn::tensor::DeviceKind::DefaultDevice,
                Some(i) => burn::tensor::DeviceKind::DiscreteGpu(i),
            })),
            #[cfg(not(feature = "gpu"))]
            Self::Gpu(_) => Err(GcnError::Device(format!(
                "device {self}: this build has no GPU support (rebuild with `--features gpu` or `--features vulkan`)"
            ))),
        }
    }
}

static CHOSEN: RwLock<ComputeDevice> = RwLock::new(ComputeDevice::Cpu);

/// Chooses the device of every later SR-GCN computation in this process. Errors (and keeps the
/// current choice) when the build cannot run on it.
pub fn select(d: ComputeDevice) -> Result<(), GcnError> {
    d.burn()?;
    *CHOSEN.write().unwrap_or_else(|p| p.into_inner()) = d;
    Ok(())
}

/// The device chosen by [`select`] (the CPU unless something chose otherwise).
pub fn chosen() -> ComputeDevice {
    *CHOSEN.read().unwrap_or_else(|p| p.into_inner())
}

/// The burn device of [`chosen`].
pub fn compute() -> Device {
    chosen().burn().unwrap_or_else(|_| Device::flex())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn device_names_parse_and_print_back() {
        for (s, d) in [
            ("cpu", ComputeDevice::Cpu),
            ("CPU", ComputeDevice::Cpu),
            ("gpu", ComputeDevice::Gpu(None)),
            ("GPU:3", ComputeDevice::Gpu(Some(3))),
        ] {
            assert_eq!(s.parse::<ComputeDevice>().unwrap(), d);
            assert_eq!(d.to_string().parse::<ComputeDevice>().unwrap(), d);
        }
        for bad in ["cuda", "gpu:", "gpu:x", "gpu0", ""] {
            let e = bad.parse::<ComputeDevice>().unwrap_err();
            assert!(matches!(e, GcnError::Device(_)), "{bad}: {e}");
            assert!(
                e.to_string().contains("expected cpu, gpu or gpu:N"),
                "{bad}: {e}"
            );
        }
        assert_eq!(ComputeDevice::Cpu.burn().unwrap(), Device::flex());
        #[cfg(not(feature = "gpu"))]
        {
            let e = select(ComputeDevice::Gpu(None)).unwrap_err();
            assert!(e.to_string().contains("--features gpu"), "{e}");
            assert_eq!(chosen(), ComputeDevice::Cpu);
        }
    }
}
