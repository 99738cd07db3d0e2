//! The wgpu device every kernel runs on: adapter choice, pipeline cache, buffer transfers.
//!
//! The pipeline has to run both on machines with a real GPU and on headless CI boxes, so the
//! adapter choice is explicit: a real GPU (discrete, then integrated, then virtual) when one is
//! there, otherwise a CPU implementation such as Mesa lavapipe (Vulkan on the CPU, package
//! `mesa-vulkan-drivers`). [`GpuConfig::adapter`] or, when that is `auto`, `RELFUSION_GPU=auto|gpu|cpu` forces a kind.

use std::collections::HashMap;
use std::fmt;
use std::str::FromStr;
use std::sync::{Mutex, mpsc};

use serde::{Deserialize, Serialize};
use wgpu::util::DeviceExt;

use crate::{Error, Result};

/// Which kind of adapter to run on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AdapterChoice {
    /// A real GPU when there is one, else a CPU adapter (the default).
    #[default]
    Auto,
    /// A real GPU (discrete, integrated or virtual); fail if there is none.
    Gpu,
    /// A CPU adapter (lavapipe / llvmpipe, WARP, ...); fail if there is none.
    Cpu,
}

impl FromStr for AdapterChoice {
    type Err = Error;

    fn from_str(s: &str) -> Result<Self> {
        match s.trim().to_ascii_lowercase().as_str() {
            "auto" | "" => Ok(Self::Auto),
            "gpu" => Ok(Self::Gpu),
            "cpu" => Ok(Self::Cpu),
            other => Err(Error::Config(format!(
                "{}={other:?}: expected auto, gpu or cpu",
                GpuConfig::ENV_VAR
            ))),
        }
    }
}

impl fmt::Display for AdapterChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Auto => "auto",
            Self::Gpu => "gpu",
            Self::Cpu => "cpu",
        })
    }
}

/// Configuration of the GPU runtime. Every field has a working default.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GpuConfig {
    /// Adapter kind (default `auto`). When it is `auto`, the environment variable
    /// [`GpuConfig::ENV_VAR`] may force `gpu` or `cpu` without editing config files; an
    /// explicit `gpu`/`cpu` here wins over the environment.
    pub adapter: AdapterChoice,
    /// Request GPU timestamp queries when the adapter supports them (default `true`); they
    /// let benchmarks separate kernel time from transfer time.
    pub timestamps: bool,
}

impl Default for GpuConfig {
    fn default() -> Self {
        Self {
            adapter: AdapterChoice::Auto,
            timestamps: true,
        }
    }
}

impl GpuConfig {
    /// Environment variable that overrides [`GpuConfig::adapter`]: `auto`, `gpu` or `cpu`.
    pub const ENV_VAR: &'static str = "RELFUSION_GPU";

    /// The adapter choice: [`GpuConfig::adapter`] if explicit, else [`GpuConfig::ENV_VAR`]
    /// if set, else `auto`.
    pub fn effective_adapter(&self) -> Result<AdapterChoice> {
        if self.adapter != AdapterChoice::Auto {
            return Ok(self.adapter);
        }
        match std::env::var(Self::ENV_VAR) {
            Ok(value) => value.parse(),
            Err(std::env::VarError::NotPresent) => Ok(self.adapter),
            Err(std::env::VarError::NotUnicode(_)) => Err(Error::Config(format!(
                "{} is not valid UTF-8",
                Self::ENV_VAR
            ))),
        }
    }
}

/// A wgpu device and queue plus the compiled compute pipelines, shared by all kernel runners.
///
/// Pipelines are compiled once per context ([`GpuContext::compute_pipeline`]); create one
/// context per process (or per worker) and keep it.
#[derive(Debug)]
pub struct GpuContext {
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    limits: wgpu::Limits,
    timestamps: bool,
    pipelines: Mutex<HashMap<String, wgpu::ComputePipeline>>,
}

impl GpuContext {
    /// Opens an adapter per `config` (see [`GpuConfig::effective_adapter`]) and creates the device.
    ///
    /// The device gets the adapter's full limits (large storage buffers for whole pyramids and
    /// depth maps) and `TIMESTAMP_QUERY` when supported and [`GpuConfig::timestamps`] is set.
    pub fn new(config: &GpuConfig) -> Result<Self> {
        Self::on_adapter(config, 0)
    }

    /// [`GpuContext::new`] on the `index`-th of the equally preferred adapters (a node with
    /// several GPUs of one kind gives each of them an index, in enumeration order).
    pub fn on_adapter(config: &GpuConfig, index: usize) -> Result<Self> {
        let choice = config.effective_adapter()?;
        let mut adapters = pollster::block_on(select_adapters(choice))?;
        let count = adapters.len();
        if index >= count {
            return Err(Error::Gpu(format!(
                "adapter {index} requested, but only {count} equally preferred adapter(s) exist"
            )));
        }
        let adapter = adapters.swap_remove(index);
        let info = adapter.get_info();
        let limits = adapter.limits();
        let timestamps =
            config.timestamps && adapter.features().contains(wgpu::Features::TIMESTAMP_QUERY);
        let required_features = if timestamps {
            wgpu::Features::TIMESTAMP_QUERY
        } else {
            wgpu::Features::empty()
        };
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("relfusion"),
            required_features,
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| Error::Gpu(format!("cannot open device on {}: {e}", describe(&info))))?;
        tracing::info!(adapter = %describe(&info), timestamps, "GPU context ready");
        Ok(Self {
            device,
            queue,
            info,
            limits,
            timestamps,
            pipelines: Mutex::new(HashMap::new()),
        })
    }

    /// Name, backend, device type and driver of the adapter in use.
    pub fn adapter_info(&self) -> &wgpu::AdapterInfo {
        &self.info
    }

    /// Limits of the device (the adapter's own limits).
    pub fn limits(&self) -> &wgpu::Limits {
        &self.limits
    }

    /// Whether the device runs on the CPU (lavapipe, llvmpipe, WARP...).
    pub fn is_cpu(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// Whether compute passes may write timestamps (`Features::TIMESTAMP_QUERY` enabled).
    pub fn supports_timestamps(&self) -> bool {
        self.timestamps
    }

    pub fn device(&self) -> &wgpu::Device {
        &self.device
    }

    pub fn queue(&self) -> &wgpu::Queue {
        &self.queue
    }

    /// The compute pipeline of kernel `name` (entry point `entry_point`, automatic layout),
    /// compiled from `source` on first use and cached under `name`; later calls with the same
    /// name return the cached pipeline without looking at `source`.
    ///
    /// Shader compilation and validation errors become [`Error::Gpu`] naming the kernel.
    pub fn compute_pipeline(
        &self,
        name: &str,
        source: &str,
        entry_point: &str,
    ) -> Result<wgpu::ComputePipeline> {
        let mut cache = self
            .pipelines
            .lock()
            .map_err(|_| Error::Gpu("pipeline cache poisoned by a panic".into()))?;
        if let Some(pipeline) = cache.get(name) {
            return Ok(pipeline.clone());
        }
        let pipeline = self.checked(&format!("kernel {name}"), || {
            let module = self
                .device
                .create_shader_module(wgpu::ShaderModuleDescriptor {
                    label: Some(name),
                    source: wgpu::ShaderSource::Wgsl(source.into()),
                });
            self.device
                .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some(name),
                    layout: None,
                    module: &module,
                    entry_point: Some(entry_point),
                    compilation_options: Default::default(),
                    cache: None,
                })
        })?;
        cache.insert(name.to_owned(), pipeline.clone());
        Ok(pipeline)
    }

    /// Runs `f` inside validation / out-of-memory / internal error scopes and turns the first
    /// captured error into [`Error::Gpu`] prefixed by `what`, instead of wgpu's default
    /// uncaptured-error panic.
    pub fn checked<T>(&self, what: &str, f: impl FnOnce() -> T) -> Result<T> {
        let internal = self.device.push_error_scope(wgpu::ErrorFilter::Internal);
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let validation = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let value = f();
        // Scopes pop in reverse order of their creation.
        let errors = [
            pollster::block_on(validation.pop()),
            pollster::block_on(oom.pop()),
            pollster::block_on(internal.pop()),
        ];
        match errors.into_iter().flatten().next() {
            Some(e) => Err(Error::Gpu(format!("{what}: {e}"))),
            None => Ok(value),
        }
    }

    /// A new storage buffer holding `data` (usable as a copy source and destination too).
    pub fn upload_f32(&self, label: &str, data: &[f32]) -> wgpu::Buffer {
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytemuck::cast_slice(data),
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_SRC
                    | wgpu::BufferUsages::COPY_DST,
            })
    }

    /// Copies `len` floats starting at float `offset` of `buffer` (which needs `COPY_SRC`) back
    /// to the host; blocks until the GPU has finished all submitted work.
    pub fn download_f32(&self, buffer: &wgpu::Buffer, offset: u64, len: usize) -> Result<Vec<f32>> {
        let bytes = (len * 4) as u64;
        if bytes == 0 {
            return Ok(Vec::new());
        }
        let staging = self.staging_buffer("download_f32", bytes);
        let mut encoder = self.device.create_command_encoder(&Default::default());
        encoder.copy_buffer_to_buffer(buffer, offset * 4, &staging, 0, bytes);
        self.checked("download_f32", || self.queue.submit([encoder.finish()]))?;
        self.read_mapped(&staging, |raw| {
            bytemuck::cast_slice::<u8, f32>(raw).to_vec()
        })
    }

    /// A `STORAGE | COPY_SRC | COPY_DST` buffer of `bytes` bytes: a kernel's input or output
    /// that is uploaded to and read back from.
    pub fn storage_buffer(&self, label: &str, bytes: u64) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: bytes,
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    /// A `MAP_READ | COPY_DST` buffer of `bytes` bytes (rounded up to the copy alignment).
    pub fn staging_buffer(&self, label: &str, bytes: u64) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: bytes.next_multiple_of(wgpu::COPY_BUFFER_ALIGNMENT),
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    /// Maps a `MAP_READ` buffer whose copy has been submitted, waits for the GPU, passes the
    /// bytes to `read` and unmaps.
    pub fn read_mapped<T>(
        &self,
        staging: &wgpu::Buffer,
        read: impl FnOnce(&[u8]) -> T,
    ) -> Result<T> {
        let (tx, rx) = mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, .., move |result| {
            // The receiver outlives the poll below; a send error only means we already gave up.
            let _ = tx.send(result);
        });
        self.wait()?;
        rx.recv()
            .map_err(|_| Error::Gpu("buffer map callback never ran".into()))?
            .map_err(|e| Error::Gpu(format!("cannot map buffer: {e}")))?;
        let value = {
            let view = staging
                .get_mapped_range(..)
                .map_err(|e| Error::Gpu(format!("cannot read mapped buffer: {e}")))?;
            read(&view)
        };
        staging.unmap();
        Ok(value)
    }

    /// Blocks until every submitted command buffer has finished (and map callbacks have run).
    pub fn wait(&self) -> Result<()> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| Error::Gpu(format!("waiting for the device: {e}")))
    }
}

/// "name (backend, device type, driver)" for messages.
fn describe(info: &wgpu::AdapterInfo) -> String {
    format!(
        "{} ({:?}, {:?}, {} {})",
        info.name, info.backend, info.device_type, info.driver, info.driver_info
    )
}

/// Preference order among adapter kinds: lower is better; `None` = not acceptable for `choice`.
fn rank(choice: AdapterChoice, info: &wgpu::AdapterInfo) -> Option<(u8, u8)> {
    use wgpu::DeviceType as T;
    if info.backend == wgpu::Backend::Noop {
        return None;
    }
    let kind = match (choice, info.device_type) {
        (AdapterChoice::Cpu, T::Cpu) => 0,
        (AdapterChoice::Cpu, _) => return None,
        (_, T::DiscreteGpu) => 0,
        (_, T::IntegratedGpu) => 1,
        (_, T::VirtualGpu) => 2,
        (AdapterChoice::Gpu, _) => return None,
        (AdapterChoice::Auto, T::Other) => 3,
        (AdapterChoice::Auto, T::Cpu) => 4,
    };
    // Among equal kinds prefer the native compute APIs over GL.
    let backend = match info.backend {
        wgpu::Backend::Vulkan | wgpu::Backend::Metal | wgpu::Backend::Dx12 => 0,
        wgpu::Backend::BrowserWebGpu => 1,
        _ => 2,
    };
    Some((kind, backend))
}

/// Enumerates adapters on the primary backends (Vulkan, Metal, DX12), then on GL only if
/// those offer none acceptable, and returns every adapter of the best [`rank`] (several on a
/// multi-GPU node), in enumeration order.
async fn select_adapters(choice: AdapterChoice) -> Result<Vec<wgpu::Adapter>> {
    let mut seen = Vec::new();
    for backends in [wgpu::Backends::PRIMARY, wgpu::Backends::SECONDARY] {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
        // WGPU_BACKEND (read by `from_env`) may narrow the set further.
        desc.backends &= backends;
        if desc.backends.is_empty() {
            continue;
        }
        let instance = wgpu::Instance::new(desc);
        let ranked: Vec<_> = instance
            .enumerate_adapters(backends)
            .await
            .into_iter()
            .filter_map(|a| {
                let info = a.get_info();
                seen.push(describe(&info));
                rank(choice, &info).map(|r| (r, a))
            })
            .collect();
        if let Some(best) = ranked.iter().map(|(r, _)| *r).min() {
            return Ok(ranked
                .into_iter()
                .filter(|(r, _)| *r == best)
                .map(|(_, a)| a)
                .collect());
        }
    }
    let hint = match choice {
        AdapterChoice::Gpu => {
            "no real GPU adapter, and adapter = gpu forbids the CPU fallback (use auto or cpu)"
        }
        _ => "no GPU adapter: install mesa-vulkan-drivers for the CPU fallback (lavapipe)",
    };
    let seen = if seen.is_empty() {
        "none".to_owned()
    } else {
        seen.join("; ")
    };
    Err(Error::Gpu(format!("{hint} [adapters seen: {seen}]")))
}

/// How many real GPUs (discrete, integrated, virtual) of the preferred kind `config` would
/// choose among: 0 on a machine with none (the CPU fallback is not counted).
pub fn gpu_adapter_count(config: &GpuConfig) -> usize {
    let Ok(choice) = config.effective_adapter() else {
        return 0;
    };
    if choice == AdapterChoice::Cpu {
        return 0;
    }
    match pollster::block_on(select_adapters(choice)) {
        Ok(adapters) => adapters
            .iter()
            .filter(|a| {
                matches!(
                    a.get_info().device_type,
                    wgpu::DeviceType::DiscreteGpu
                        | wgpu::DeviceType::IntegratedGpu
                        | wgpu::DeviceType::VirtualGpu
                )
            })
            .count(),
        Err(_) => 0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn info(device_type: wgpu::DeviceType, backend: wgpu::Backend) -> wgpu::AdapterInfo {
        wgpu::AdapterInfo::new(device_type, backend)
    }

    #[test]
    fn gpu_adapter_choice_parses_and_rejects_garbage() {
        assert_eq!(
            "CPU".parse::<AdapterChoice>().expect("cpu"),
            AdapterChoice::Cpu
        );
        assert_eq!(
            " gpu ".parse::<AdapterChoice>().expect("gpu"),
            AdapterChoice::Gpu
        );
        assert_eq!(
            "auto".parse::<AdapterChoice>().expect("auto"),
            AdapterChoice::Auto
        );
        assert!(matches!(
            "fast".parse::<AdapterChoice>(),
            Err(Error::Config(_))
        ));
    }

    #[test]
    fn gpu_rank_prefers_real_gpus_and_honours_forced_kinds() {
        use wgpu::{Backend as B, DeviceType as T};
        let discrete = info(T::DiscreteGpu, B::Vulkan);
        let integrated = info(T::IntegratedGpu, B::Vulkan);
        let cpu = info(T::Cpu, B::Vulkan);
        let cpu_gl = info(T::Cpu, B::Gl);
        let auto = AdapterChoice::Auto;
        assert!(rank(auto, &discrete) < rank(auto, &integrated));
        assert!(rank(auto, &integrated) < rank(auto, &cpu));
        assert!(rank(auto, &cpu) < rank(auto, &cpu_gl));
        assert_eq!(rank(AdapterChoice::Gpu, &cpu), None);
        assert_eq!(rank(AdapterChoice::Cpu, &discrete), None);
        assert!(rank(AdapterChoice::Cpu, &cpu).is_some());
        assert_eq!(rank(auto, &info(T::Cpu, B::Noop)), None);
    }

    #[test]
    fn gpu_adapters_are_indexed_and_a_missing_index_is_an_error() {
        let config = GpuConfig::default();
        let first = GpuContext::on_adapter(&config, 0).expect("an adapter (lavapipe at least)");
        let same = crate::gpu::context_for(0).expect("cached");
        assert_eq!(first.adapter_info().name, same.adapter_info().name);
        assert!(std::sync::Arc::ptr_eq(
            &same,
            &crate::gpu::shared_context().expect("shared")
        ));
        let err = GpuContext::on_adapter(&config, 1000).expect_err("no 1001st adapter");
        assert!(err.to_string().contains("adapter 1000"), "{err}");
        assert!(crate::gpu::context_for(1000).is_err());
    }

    #[test]
    fn gpu_config_defaults_and_rejects_unknown_fields() {
        let config: GpuConfig = serde_json::from_str("{}").expect("empty config");
        assert_eq!(config.adapter, AdapterChoice::Auto);
        assert!(config.timestamps);
        let forced: GpuConfig = serde_json::from_str(r#"{"adapter":"cpu"}"#).expect("cpu");
        assert_eq!(forced.adapter, AdapterChoice::Cpu);
        assert!(serde_json::from_str::<GpuConfig>(r#"{"adaptor":"cpu"}"#).is_err());
        // An explicit choice is final, whatever RELFUSION_GPU says.
        assert_eq!(
            forced.effective_adapter().expect("explicit"),
            AdapterChoice::Cpu
        );
    }
}
