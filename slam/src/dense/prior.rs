//! The depth prior `D_CNN` of DeepRelativeFusion §III-B: a single-image network that predicts
//! a *relative inverse depth* map for each keyframe, run with ONNX Runtime.
//!
//! The paper uses MiDaS v2.1 (inverse depth up to scale and shift). Any MiDaS-style ONNX model
//! can be used: known ones are recognised from the file ([`super::model_config::recognise`]),
//! others need a [`ModelConfig`]. Models that predict depth rather than inverse depth (the
//! PyDNet++ stand-in of the shared test data, FastDepth's metres) are inverted (`1 / pred`) so that every prior
//! hands the dense layer the same quantity; eq. (3)'s affine correction is only meaningful in
//! inverse-depth space, where the scale- and shift-invariant training of MiDaS lives.
//!
//! ## ONNX Runtime
//! The runtime is loaded dynamically (ort `load-dynamic`) once per process, from the first of:
//! 1. `$ORT_DYLIB_PATH`, if set (an error if that file does not exist: no silent fallback);
//! 2. `${XDG_CACHE_HOME:-$HOME/.cache}/relfusion/onnxruntime-1.31.1/onnxruntime/capi/libonnxruntime.so.1.31.1`
//!    (where `make setup` installs it);
//! 3. `/opt/relfusion/ort/onnxruntime/capi/libonnxruntime.so.1.31.1`.

use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use ort::environment::Environment;
use ort::session::builder::GraphOptimizationLevel;
use ort::session::{HasSelectedOutputs, OutputSelector, RunOptions, Session};
use ort::value::{Outlet, Tensor, TensorElementType};
use sha2::{Digest, Sha256};

use super::model_config::{
    Layout, ModelConfig, ModelSignature, OutputKind, Recognition, ResizeMode, TensorInfo, recognise,
};
use crate::image::ImageF32;
use crate::{Error, Result};

/// ONNX Runtime version the `ort` binding targets (API 31) and that `make setup` installs.
pub const ORT_VERSION: &str = "1.31.1";
/// Environment variable naming the ONNX Runtime shared library (also read by `ort` itself).
pub const ORT_DYLIB_ENV: &str = "ORT_DYLIB_PATH";
/// System-wide fallback location of the runtime library.
pub const ORT_SYSTEM_PATH: &str = "/opt/relfusion/ort/onnxruntime/capi/libonnxruntime.so.1.31.1";

/// A relative inverse-depth map (`D_CNN`, larger = nearer) at the resolution of the image it
/// was predicted from. Its scale and shift are unknown until aligned with eq. (3)
/// ([`crate::scale_shift::fit_scale_shift`]). Pixels without a usable prediction hold 0.
#[derive(Clone, Debug, PartialEq)]
pub struct InverseDepth(pub ImageF32);

impl InverseDepth {
    /// The map as an image.
    pub fn image(&self) -> &ImageF32 {
        &self.0
    }
    /// Unwraps the map.
    pub fn into_image(self) -> ImageF32 {
        self.0
    }
}

/// A single-image relative depth predictor (the paper's `D_CNN` source).
pub trait DepthPrior: Send + std::fmt::Debug {
    /// Predicts the relative inverse depth of `rgb`, returned at `rgb`'s resolution.
    fn predict(&mut self, rgb: &::image::RgbImage) -> Result<InverseDepth>;
    /// How the model is fed and read.
    fn describe(&self) -> &ModelConfig;
}

/// The default location of the runtime library under the user cache directory, from
/// `XDG_CACHE_HOME` or `HOME` (`None` when neither is set).
pub fn default_cache_library_path(
    xdg_cache_home: Option<OsString>,
    home: Option<OsString>,
) -> Option<PathBuf> {
    let cache = match (
        xdg_cache_home.filter(|v| !v.is_empty()),
        home.filter(|v| !v.is_empty()),
    ) {
        (Some(xdg), _) => PathBuf::from(xdg),
        (None, Some(home)) => PathBuf::from(home).join(".cache"),
        (None, None) => return None,
    };
    Some(
        cache
            .join("relfusion")
            .join(format!("onnxruntime-{ORT_VERSION}"))
            .join("onnxruntime/capi")
            .join(format!("libonnxruntime.so.{ORT_VERSION}")),
    )
}

/// Resolves the runtime library from the process environment (see the module docs for the
/// order). Fails with [`Error::Prior`] naming every place searched.
pub fn runtime_library_path() -> Result<PathBuf> {
    resolve_library(
        std::env::var_os(ORT_DYLIB_ENV),
        default_cache_library_path(std::env::var_os("XDG_CACHE_HOME"), std::env::var_os("HOME")),
        Path::new(ORT_SYSTEM_PATH),
    )
}

/// The resolution rule of [`runtime_library_path`] with its inputs made explicit (testable).
pub fn resolve_library(
    env_override: Option<OsString>,
    cache_path: Option<PathBuf>,
    system_path: &Path,
) -> Result<PathBuf> {
    if let Some(path) = env_override.filter(|v| !v.is_empty()).map(PathBuf::from) {
        return if path.is_file() {
            Ok(path)
        } else {
            Err(missing_runtime(&[path]))
        };
    }
    let candidates: Vec<PathBuf> = cache_path
        .into_iter()
        .chain(std::iter::once(system_path.to_path_buf()))
        .collect();
    candidates
        .iter()
        .find(|p| p.is_file())
        .cloned()
        .ok_or_else(|| missing_runtime(&candidates))
}

fn missing_runtime(searched: &[PathBuf]) -> Error {
    let list: Vec<String> = searched.iter().map(|p| p.display().to_string()).collect();
    Error::Prior(format!(
        "ONNX Runtime library not found at {}; run `make setup` or set {ORT_DYLIB_ENV}",
        list.join(" or ")
    ))
}

static ENVIRONMENT: OnceLock<Environment> = OnceLock::new();
static INIT: Mutex<()> = Mutex::new(());

/// Loads ONNX Runtime from `library` (or from [`runtime_library_path`] when `None`) and
/// creates the process-wide environment, once. Later calls return the same environment; the
/// library of the first successful call stays loaded.
///
/// Fails (never panics) when the library file does not exist, cannot be loaded, or is too old.
pub fn init_runtime(library: Option<&Path>) -> Result<&'static Environment> {
    let path = match library {
        Some(p) if p.is_file() => p.to_path_buf(),
        Some(p) => return Err(missing_runtime(&[p.to_path_buf()])),
        None => runtime_library_path()?,
    };
    if let Some(env) = ENVIRONMENT.get() {
        return Ok(env);
    }
    let _guard = INIT
        .lock()
        .map_err(|_| Error::Prior("runtime init lock poisoned".into()))?;
    if let Some(env) = ENVIRONMENT.get() {
        return Ok(env);
    }
    // `ort` validates the library and its version here and reports failures as errors; the
    // catch_unwind is a second line of defence, since `ort` panics if its API is used after a
    // failed load.
    let built = std::panic::catch_unwind(|| -> Result<Environment> {
        let builder = ort::init_from(&path).map_err(|e| {
            Error::Prior(format!(
                "cannot load ONNX Runtime from {}: {e}",
                path.display()
            ))
        })?;
        builder
            .with_name("relfusion")
            .with_telemetry(false)
            .build()
            .map_err(|e| Error::Prior(format!("cannot create the ONNX Runtime environment: {e}")))
    })
    .map_err(|_| {
        Error::Prior(format!(
            "ONNX Runtime panicked while loading {}",
            path.display()
        ))
    })??;
    tracing::info!(library = %path.display(), "ONNX Runtime loaded");
    Ok(ENVIRONMENT.get_or_init(|| built))
}

/// A depth prior backed by an ONNX model.
pub struct OnnxDepthPrior {
    session: Session,
    run_options: RunOptions<HasSelectedOutputs>,
    config: ModelConfig,
    recognition: Recognition,
    signature: ModelSignature,
    sha256: String,
}

impl std::fmt::Debug for OnnxDepthPrior {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OnnxDepthPrior")
            .field("config", &self.config)
            .field("recognition", &self.recognition)
            .field("signature", &self.signature)
            .field("sha256", &self.sha256)
            .finish_non_exhaustive()
    }
}

/// How [`OnnxDepthPrior::load_with`] opens a model beyond its [`ModelConfig`].
#[derive(Clone, Debug, Default)]
pub struct LoadOptions {
    /// The ONNX Runtime library (`None`: [`runtime_library_path`]).
    pub runtime_library: Option<PathBuf>,
    /// Intra-op threads, replacing the config's (or the recognised model's) own. One thread
    /// on a machine whose cores are all busy: ONNX Runtime's parallel sections spin-wait for
    /// a descheduled worker (docs/build-time.md, "ONNX Runtime's waits under load").
    pub intra_threads: Option<usize>,
}

impl OnnxDepthPrior {
    /// Loads `model_path` with the runtime found by [`runtime_library_path`]. With `config`,
    /// the config is checked against the model's inputs and outputs; without, the model must
    /// be one [`recognise`] knows.
    pub fn load(model_path: &Path, config: Option<ModelConfig>) -> Result<Self> {
        Self::load_with(model_path, config, &LoadOptions::default())
    }

    /// [`Self::load`] with [`LoadOptions`]: another runtime library, another thread count.
    pub fn load_with(
        model_path: &Path,
        config: Option<ModelConfig>,
        options: &LoadOptions,
    ) -> Result<Self> {
        // Check the model first: a missing model is the more specific error.
        if !model_path.is_file() {
            return Err(Error::Prior(format!(
                "model file {} not found",
                model_path.display()
            )));
        }
        if options.intra_threads == Some(0) {
            return Err(Error::Prior("intra_threads must be at least 1".into()));
        }
        let bytes = std::fs::read(model_path).map_err(|e| Error::io(model_path, e))?;
        let sha256 = hex(&Sha256::digest(&bytes));
        let env = init_runtime(options.runtime_library.as_deref())?;
        // Recognised models use the ModelConfig default of 2 intra-op threads.
        let threads = options
            .intra_threads
            .unwrap_or_else(|| config.as_ref().map_or(2, |c| c.intra_threads));
        let session = build_session(env, &bytes, threads)
            .map_err(|e| Error::Prior(format!("{}: {e}", model_path.display())))?;
        let signature = signature(&session);
        let file_name = model_path
            .file_name()
            .map(|n| n.to_string_lossy())
            .unwrap_or_default();
        let (config, recognition) = match config {
            Some(c) => (c, Recognition::UserConfig),
            None => recognise(&signature, &sha256, &file_name).ok_or_else(|| {
                Error::Prior(format!(
                    "{} is not a model relfusion recognises; describe it with --model-config \
                     (a TOML/JSON ModelConfig: input name and size, layout, scale, mean/std, \
                     output name and kind). The model has {signature}",
                    model_path.display()
                ))
            })?,
        };
        let config = ModelConfig {
            intra_threads: threads,
            ..config
        };
        config.validate(&signature)?;
        let run_options = RunOptions::new()
            .map_err(|e| Error::Prior(format!("run options: {e}")))?
            .with_outputs(OutputSelector::no_default().with(config.output.clone()));
        tracing::info!(model = %config.name, ?recognition, "depth prior loaded");
        Ok(Self {
            session,
            run_options,
            config,
            recognition,
            signature,
            sha256,
        })
    }

    /// How the config was obtained.
    pub fn recognition(&self) -> Recognition {
        self.recognition
    }

    /// The model's real inputs and outputs.
    pub fn signature(&self) -> &ModelSignature {
        &self.signature
    }

    /// sha256 of the model file (lower-case hex).
    pub fn sha256(&self) -> &str {
        &self.sha256
    }

    /// Runs the network on an already preprocessed tensor and returns the raw output map at
    /// the network's resolution.
    fn run(&mut self, input: Vec<f32>, (w, h): (usize, usize)) -> Result<ImageF32> {
        let shape = match self.config.layout {
            Layout::Nchw => [1, 3, h, w],
            Layout::Nhwc => [1, h, w, 3],
        };
        let tensor = Tensor::from_array((shape, input))
            .map_err(|e| Error::Prior(format!("input tensor: {e}")))?;
        let name = self.config.input.as_str();
        let outputs = self
            .session
            .run_with_options(ort::inputs![name => tensor], &self.run_options)
            .map_err(|e| {
                Error::Prior(format!("inference of `{}` failed: {e}", self.config.name))
            })?;
        let value = outputs.get(&self.config.output).ok_or_else(|| {
            Error::Prior(format!(
                "the model produced no output `{}`",
                self.config.output
            ))
        })?;
        let (shape, data) = value
            .try_extract_tensor::<f32>()
            .map_err(|e| Error::Prior(format!("output `{}`: {e}", self.config.output)))?;
        let (oh, ow) = spatial_dims(shape)?;
        ImageF32::from_vec(ow, oh, data.to_vec()).map_err(Into::into)
    }
}

impl DepthPrior for OnnxDepthPrior {
    fn predict(&mut self, rgb: &::image::RgbImage) -> Result<InverseDepth> {
        let (w, h) = (rgb.width() as usize, rgb.height() as usize);
        if w == 0 || h == 0 {
            return Err(Error::Shape(
                "cannot predict depth of an empty image".into(),
            ));
        }
        let net = network_size(&self.config, w, h);
        let input = preprocess(rgb, &self.config, net);
        let raw = self.run(input, net)?;
        // Resize first, then invert (shared data README §1.4): the dense layer works per pixel of
        // the keyframe, and bilinear interpolation of the raw output is what the network's own
        // decoder does.
        let mut map = resize_bilinear(&raw.data, raw.width, raw.height, 1, w, h);
        for v in &mut map {
            *v = match self.config.output_kind {
                OutputKind::InverseDepth | OutputKind::Disparity if v.is_finite() => *v,
                OutputKind::Depth if v.is_finite() && *v > 0.0 => 1.0 / *v,
                _ => 0.0,
            };
        }
        Ok(InverseDepth(ImageF32::from_vec(w, h, map)?))
    }

    fn describe(&self) -> &ModelConfig {
        &self.config
    }
}

/// Builds the session on a background-priority thread: ONNX Runtime starts its intra-op pool
/// threads here and they inherit the creating thread's priority, so inference (always
/// background work: the dense layer, the server's GPU pool) never outranks tracking.
fn build_session(env: &Environment, bytes: &[u8], threads: usize) -> ort::Result<Session> {
    std::thread::scope(|scope| {
        scope
            .spawn(|| {
                crate::background::lower_current_thread_priority(
                    crate::background::Priority::Dense,
                );
                session_builder(env, bytes, threads)
            })
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
    })
}

fn session_builder(env: &Environment, bytes: &[u8], threads: usize) -> ort::Result<Session> {
    let mut builder = Session::builder(env)?;
    // The GPU build of ONNX Runtime (`onnxruntime-gpu`, the image's `ORT_PACKAGE` build
    // argument) offers CUDA: inference then runs there. The CPU build does not list it, and
    // nothing is tried.
    use ort::ep::ExecutionProvider as _;
    if ort::ep::CUDA::is_available().unwrap_or(false) {
        builder = builder
            .with_execution_providers([ort::ep::CUDA::default().build()])
            .map_err(ort::Error::<()>::from)?;
    }
    builder
        .with_optimization_level(GraphOptimizationLevel::Level3)?
        .with_intra_threads(threads)?
        // Idle pool threads sleep instead of spinning: a spinning thread takes a core from
        // tracking between keyframes.
        .with_intra_op_spinning(false)?
        .commit_from_memory(bytes)
}

fn tensor_info(outlet: &Outlet) -> TensorInfo {
    let dtype = outlet.dtype();
    TensorInfo {
        name: outlet.name().to_string(),
        shape: dtype.tensor_shape().map(|s| s.iter().copied().collect()),
        is_f32: dtype.tensor_type() == Some(TensorElementType::Float32),
    }
}

fn signature(session: &Session) -> ModelSignature {
    ModelSignature {
        inputs: session.inputs().iter().map(tensor_info).collect(),
        outputs: session.outputs().iter().map(tensor_info).collect(),
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// `(height, width)` of an output tensor shaped `[H, W]`, `[1, H, W]`, `[1, 1, H, W]` or
/// `[1, H, W, 1]`.
fn spatial_dims(shape: &[i64]) -> Result<(usize, usize)> {
    let mut dims: Vec<i64> = shape.to_vec();
    if dims.len() > 2 && dims.last() == Some(&1) {
        dims.pop();
    }
    while dims.len() > 2 && dims[0] == 1 {
        dims.remove(0);
    }
    match dims.as_slice() {
        [h, w] if *h > 0 && *w > 0 => Ok((*h as usize, *w as usize)),
        _ => Err(Error::Prior(format!(
            "output shape {shape:?} is not a single-channel map ([H,W], [1,H,W], [1,1,H,W] or \
             [1,H,W,1])"
        ))),
    }
}

/// The `(width, height)` fed to the network for a `w × h` image ([`ResizeMode`]).
pub fn network_size(config: &ModelConfig, w: usize, h: usize) -> (usize, usize) {
    let (tw, th) = (config.input_width as usize, config.input_height as usize);
    match config.resize {
        ResizeMode::Stretch => (tw, th),
        ResizeMode::KeepAspect => {
            let scale = (tw as f64 / w as f64).max(th as f64 / h as f64);
            let m = config.multiple_of.unwrap_or(1).max(1) as f64;
            // Lower bound: round to the multiple, but never below the target size.
            let side = |x: f64, min: usize| {
                let rounded = (x / m).round() * m;
                let side = if rounded < min as f64 {
                    (x / m).ceil() * m
                } else {
                    rounded
                };
                side.max(m) as usize
            };
            (side(w as f64 * scale, tw), side(h as f64 * scale, th))
        }
    }
}

/// Resizes `rgb` to `net` and normalises it (`(c·scale − mean) / std`) into the tensor layout.
pub fn preprocess(rgb: &::image::RgbImage, config: &ModelConfig, net: (usize, usize)) -> Vec<f32> {
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    let src: Vec<f32> = rgb.as_raw().iter().map(|&v| f32::from(v)).collect();
    let resized = resize_bilinear(&src, w, h, 3, net.0, net.1);
    let n = net.0 * net.1;
    let mut out = vec![0.0f32; 3 * n];
    let gain: [f32; 3] = std::array::from_fn(|c| config.scale / config.std[c]);
    let offset: [f32; 3] = std::array::from_fn(|c| config.mean[c] / config.std[c]);
    for (i, px) in resized.chunks_exact(3).enumerate() {
        for c in 0..3 {
            let v = px[c] * gain[c] - offset[c];
            match config.layout {
                Layout::Nchw => out[c * n + i] = v,
                Layout::Nhwc => out[3 * i + c] = v,
            }
        }
    }
    out
}

/// Bilinear resize of an interleaved `channels`-channel image with pixel-centre alignment
/// (OpenCV `INTER_LINEAR`, PyTorch `align_corners=False`), edges clamped.
pub fn resize_bilinear(
    src: &[f32],
    sw: usize,
    sh: usize,
    channels: usize,
    dw: usize,
    dh: usize,
) -> Vec<f32> {
    if (sw, sh) == (dw, dh) {
        return src.to_vec();
    }
    let axis = |d: usize, s: usize| -> Vec<(usize, usize, f32)> {
        let ratio = s as f32 / d as f32;
        (0..d)
            .map(|i| {
                let x = ((i as f32 + 0.5) * ratio - 0.5).clamp(0.0, (s - 1) as f32);
                let x0 = x.floor() as usize;
                let x1 = (x0 + 1).min(s - 1);
                (x0, x1, x - x0 as f32)
            })
            .collect()
    };
    let (xs, ys) = (axis(dw, sw), axis(dh, sh));
    let mut out = vec![0.0f32; dw * dh * channels];
    for (y, &(y0, y1, fy)) in ys.iter().enumerate() {
        let (r0, r1) = (&src[y0 * sw * channels..], &src[y1 * sw * channels..]);
        let row = &mut out[y * dw * channels..(y + 1) * dw * channels];
        for (x, &(x0, x1, fx)) in xs.iter().enumerate() {
            for c in 0..channels {
                let top = r0[x0 * channels + c] * (1.0 - fx) + r0[x1 * channels + c] * fx;
                let bottom = r1[x0 * channels + c] * (1.0 - fx) + r1[x1 * channels + c] * fx;
                row[x * channels + c] = top * (1.0 - fy) + bottom * fy;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dense::model_config::OutputKind;

    fn config(resize: ResizeMode, multiple_of: Option<u32>) -> ModelConfig {
        ModelConfig {
            name: "t".into(),
            input: "x".into(),
            input_width: 518,
            input_height: 518,
            multiple_of,
            layout: Layout::Nchw,
            scale: 1.0 / 255.0,
            mean: [0.5, 0.25, 0.0],
            std: [0.5, 0.5, 2.0],
            output: "y".into(),
            output_kind: OutputKind::InverseDepth,
            metric: false,
            resize,
            intra_threads: 2,
        }
    }

    #[test]
    fn dense_resize_bilinear_matches_pixel_centre_convention() {
        // Upsampling 2 → 4 with centre alignment: the outer pixels clamp, inner ones blend 3:1.
        let out = resize_bilinear(&[0.0, 4.0], 2, 1, 1, 4, 1);
        assert_eq!(out, vec![0.0, 1.0, 3.0, 4.0]);
        // Identity size is a copy; a constant stays constant at any size.
        assert_eq!(resize_bilinear(&[1.0, 2.0], 2, 1, 1, 2, 1), vec![1.0, 2.0]);
        let flat = resize_bilinear(&[7.0; 3 * 6], 3, 2, 3, 5, 7);
        assert!(flat.iter().all(|&v| (v - 7.0).abs() < 1e-6));
    }

    #[test]
    fn dense_network_size_follows_resize_mode() {
        assert_eq!(
            network_size(&config(ResizeMode::Stretch, None), 640, 480),
            (518, 518)
        );
        // Depth Anything lower bound: 480 → 518, 640·518/480 = 690.7 → 686 (multiple of 14).
        let (w, h) = network_size(&config(ResizeMode::KeepAspect, Some(14)), 640, 480);
        assert_eq!((w, h), (686, 518));
        assert!(w % 14 == 0 && h % 14 == 0 && w >= 518 && h >= 518);
    }

    #[test]
    fn dense_preprocess_normalises_into_layout() {
        let rgb = ::image::RgbImage::from_pixel(2, 2, ::image::Rgb([255, 51, 0]));
        let mut c = config(ResizeMode::Stretch, None);
        c.input_width = 2;
        c.input_height = 2;
        let nchw = preprocess(&rgb, &c, (2, 2));
        // R: (1 − 0.5)/0.5 = 1; G: (0.2 − 0.25)/0.5 = −0.1; B: (0 − 0)/2 = 0.
        assert!(nchw[..4].iter().all(|&v| (v - 1.0).abs() < 1e-6));
        assert!(nchw[4..8].iter().all(|&v| (v + 0.1).abs() < 1e-6));
        assert!(nchw[8..].iter().all(|&v| v.abs() < 1e-6));
        c.layout = Layout::Nhwc;
        let nhwc = preprocess(&rgb, &c, (2, 2));
        assert!((nhwc[0] - 1.0).abs() < 1e-6 && (nhwc[1] + 0.1).abs() < 1e-6);
    }

    #[test]
    fn dense_output_shapes_are_understood() {
        assert_eq!(spatial_dims(&[1, 1, 448, 640]).expect("nchw"), (448, 640));
        assert_eq!(spatial_dims(&[1, 256, 256]).expect("chw"), (256, 256));
        assert_eq!(spatial_dims(&[1, 30, 40, 1]).expect("nhwc"), (30, 40));
        assert_eq!(spatial_dims(&[30, 40]).expect("hw"), (30, 40));
        assert!(spatial_dims(&[1, 3, 30, 40]).is_err());
    }

    #[test]
    fn dense_runtime_resolution_order() {
        let dir = std::env::temp_dir().join(format!("relfusion-ort-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let present = dir.join("libonnxruntime.so");
        std::fs::write(&present, b"not really a library").expect("write");
        let absent = dir.join("missing.so");
        // An explicit override wins, and must exist.
        let got = resolve_library(Some(present.clone().into()), None, &absent).expect("override");
        assert_eq!(got, present);
        let err = resolve_library(Some(absent.clone().into()), Some(present.clone()), &present)
            .expect_err("missing override is an error, not a fallback")
            .to_string();
        assert!(
            err.contains("not found") && err.contains("ORT_DYLIB_PATH"),
            "{err}"
        );
        // Then the cache location, then the system one.
        assert_eq!(
            resolve_library(None, Some(present.clone()), &absent).expect("cache"),
            present
        );
        assert_eq!(
            resolve_library(None, Some(absent.clone()), &present).expect("system"),
            present
        );
        let err = resolve_library(None, Some(absent.clone()), &absent).expect_err("none");
        assert!(err.to_string().contains("make setup"), "{err}");
        // XDG_CACHE_HOME beats HOME.
        let p = default_cache_library_path(Some("/x".into()), Some("/h".into())).expect("path");
        assert!(
            p.starts_with("/x/relfusion/onnxruntime-1.31.1"),
            "{}",
            p.display()
        );
        let p = default_cache_library_path(None, Some("/h".into())).expect("path");
        assert!(p.starts_with("/h/.cache/relfusion"), "{}", p.display());
        assert!(default_cache_library_path(None, None).is_none());
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn dense_missing_runtime_library_is_an_error() {
        let err = init_runtime(Some(Path::new("/nonexistent/relfusion/libonnxruntime.so")))
            .expect_err("missing library must be an error");
        let msg = err.to_string();
        assert!(
            msg.contains("ONNX Runtime library not found at /nonexistent"),
            "{msg}"
        );
    }
}
