//! How to feed a depth-prior ONNX model and how to read its output ([`ModelConfig`]), the
//! models recognised without a config ([`recognise`]), and the check of a config against the
//! model's real inputs and outputs ([`ModelConfig::validate`]).
//!
//! A config is a small TOML or JSON file (`--model-config`), e.g. for a MiDaS-style export:
//!
//! ```toml
//! name = "my_midas"
//! input = "input"
//! input_width = 256
//! input_height = 256
//! mean = [0.485, 0.456, 0.406]
//! std = [0.229, 0.224, 0.225]
//! output = "output"
//! output_kind = "inverse_depth"
//! ```
//!
//! Fields not given take the defaults documented on [`ModelConfig`]; unknown fields are
//! rejected so that a typo cannot silently fall back to a default.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::{Error, Result};

/// sha256 of `pydnet_pp_matterport_448x640_nchw_fp32.onnx`, the PyDNet++ stand-in of the shared
/// test data (shared data README §1.2).
pub const PYDNET_PP_SHA256: &str =
    "92110c96b3d5781ab5fd2b3901451053cb13c130c6df04fdec88d53f41f81f36";

/// sha256 of `fastdepth_224x224_op13.onnx`, the official FastDepth weights (NYU Depth v2,
/// metric depth) of the shared test data (shared data README §5).
pub const FASTDEPTH_NYU_SHA256: &str =
    "5e1be63dd3f659297a5b9f0c3f7312652735ad8d59fccf485bc95e5cb2440bba";

/// sha256 of `model-small.onnx` from the MiDaS `v2_1` GitHub release (MiDaS v2.1 small, 256×256).
pub const MIDAS_V21_SMALL_RELEASE_SHA256: &str =
    "2d8c6cb8f415229daf1eb041024208e2608c9f98e17c81cc7c6ecb449c56fd58";

/// ImageNet channel means (RGB in [0, 1]) used by MiDaS v2.1 and Depth Anything.
pub const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
/// ImageNet channel standard deviations (RGB in [0, 1]).
pub const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// Memory order of the image tensor.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Layout {
    /// `[1, 3, H, W]` (PyTorch exports; the default).
    #[default]
    Nchw,
    /// `[1, H, W, 3]` (TensorFlow exports).
    Nhwc,
}

/// What the output tensor holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OutputKind {
    /// Depth-like values (larger = farther), e.g. PyDNet, FastDepth (metres); the runtime takes
    /// `1 / value`.
    Depth,
    /// Inverse depth (larger = nearer), e.g. MiDaS, Depth Anything.
    InverseDepth,
    /// Disparity (larger = nearer; inverse depth up to a scale the model does not know, e.g.
    /// a stereo-trained network): read as relative inverse depth.
    Disparity,
}

impl OutputKind {
    /// Whether values grow with distance (the runtime then takes `1 / value`).
    pub fn grows_with_distance(self) -> bool {
        self == Self::Depth
    }
}

/// How the camera image is brought to the network input size.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ResizeMode {
    /// Resize to exactly `input_width × input_height`, ignoring the aspect ratio (the default;
    /// the only choice for fixed-size inputs, as in MiDaS's ONNX `run_onnx.py`).
    #[default]
    Stretch,
    /// For models with dynamic spatial dimensions: keep the aspect ratio and scale the image so
    /// that both sides are at least `input_width`/`input_height`, each side rounded to a
    /// multiple of `multiple_of` (MiDaS / Depth Anything `Resize(keep_aspect_ratio=True,
    /// resize_method="lower_bound")`).
    KeepAspect,
}

/// How to run one depth-prior model. Loadable from TOML or JSON ([`ModelConfig::from_file`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelConfig {
    /// Name reported in logs and benchmark output.
    pub name: String,
    /// Name of the image input tensor.
    pub input: String,
    /// Network input width in pixels (the exact width for [`ResizeMode::Stretch`], the lower
    /// bound for [`ResizeMode::KeepAspect`]).
    pub input_width: u32,
    /// Network input height in pixels.
    pub input_height: u32,
    /// For dynamic-size inputs: both sides fed to the network are multiples of this (e.g. 14
    /// for ViT-S/14 Depth Anything, 32 for MiDaS). Default: none.
    #[serde(default)]
    pub multiple_of: Option<u32>,
    /// Default: [`Layout::Nchw`].
    #[serde(default)]
    pub layout: Layout,
    /// Factor applied to 8-bit RGB before mean/std. Default: 1/255 (RGB in [0, 1]).
    #[serde(default = "default_scale")]
    pub scale: f32,
    /// Per-channel (R, G, B) mean subtracted after scaling. Default: 0.
    #[serde(default = "default_mean")]
    pub mean: [f32; 3],
    /// Per-channel standard deviation divided after the mean. Default: 1.
    #[serde(default = "default_std")]
    pub std: [f32; 3],
    /// Name of the output tensor holding the prediction.
    pub output: String,
    /// Whether the output is depth-like or inverse depth.
    pub output_kind: OutputKind,
    /// Whether the output is in metres (a metric network such as FastDepth, Depth Anything
    /// metric, UniDepth) rather than up to an unknown scale and shift (MiDaS-style). A metric
    /// prior anchors the map's scale (`backend.metric_scale`); a relative one never does.
    /// Default false.
    #[serde(default)]
    pub metric: bool,
    /// Default: [`ResizeMode::Stretch`].
    #[serde(default)]
    pub resize: ResizeMode,
    /// ONNX Runtime intra-op threads. Default: 2 (the pipeline runs tracking and mapping on
    /// other threads; a prior that takes every core starves them).
    #[serde(default = "default_threads")]
    pub intra_threads: usize,
}

fn default_scale() -> f32 {
    1.0 / 255.0
}
fn default_mean() -> [f32; 3] {
    [0.0; 3]
}
fn default_std() -> [f32; 3] {
    [1.0; 3]
}
fn default_threads() -> usize {
    2
}

/// One input or output of a model as ONNX Runtime reports it. Dimensions are `-1` where the
/// model leaves them dynamic.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TensorInfo {
    pub name: String,
    /// `None` when the value is not a tensor (sequence, map).
    pub shape: Option<Vec<i64>>,
    /// Whether the element type is `float32`.
    pub is_f32: bool,
}

/// The inputs and outputs of a model; what configs are checked against.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ModelSignature {
    pub inputs: Vec<TensorInfo>,
    pub outputs: Vec<TensorInfo>,
}

impl std::fmt::Display for TensorInfo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let ty = if self.is_f32 { "f32" } else { "non-f32" };
        match &self.shape {
            Some(s) => {
                let dims: Vec<String> = s
                    .iter()
                    .map(|&d| if d < 0 { "?".into() } else { d.to_string() })
                    .collect();
                write!(f, "`{}` {ty} [{}]", self.name, dims.join(", "))
            }
            None => write!(f, "`{}` (not a tensor)", self.name),
        }
    }
}

impl std::fmt::Display for ModelSignature {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let list = |v: &[TensorInfo]| v.iter().map(ToString::to_string).collect::<Vec<_>>();
        write!(
            f,
            "inputs: {}; outputs: {}",
            list(&self.inputs).join(", "),
            list(&self.outputs).join(", ")
        )
    }
}

impl ModelSignature {
    fn input(&self, name: &str) -> Option<&TensorInfo> {
        self.inputs.iter().find(|t| t.name == name)
    }
    fn output(&self, name: &str) -> Option<&TensorInfo> {
        self.outputs.iter().find(|t| t.name == name)
    }
}

impl ModelConfig {
    /// Reads a config from a `.toml` or `.json` file (chosen by extension).
    pub fn from_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        let parsed = match ext.as_deref() {
            Some("toml") => Self::from_toml(&text),
            Some("json") => Self::from_json(&text),
            _ => Err(Error::Config(
                "model config must be a .toml or .json file".into(),
            )),
        };
        parsed.map_err(|e| match e {
            Error::Config(msg) => Error::Config(format!("{}: {msg}", path.display())),
            other => other,
        })
    }

    /// Parses a TOML config.
    pub fn from_toml(text: &str) -> Result<Self> {
        let config: Self = toml::from_str(text).map_err(|e| Error::Config(e.to_string()))?;
        config.check_values()?;
        Ok(config)
    }

    /// Parses a JSON config.
    pub fn from_json(text: &str) -> Result<Self> {
        let config: Self = serde_json::from_str(text).map_err(|e| Error::Config(e.to_string()))?;
        config.check_values()?;
        Ok(config)
    }

    /// Value checks that need no model: positive sizes, finite scale, positive std, threads.
    pub fn check_values(&self) -> Result<()> {
        let bad = |msg: String| Err(Error::Config(format!("model `{}`: {msg}", self.name)));
        if self.input_width == 0 || self.input_height == 0 {
            return bad(format!(
                "input size {}x{} is empty",
                self.input_width, self.input_height
            ));
        }
        if !(self.scale.is_finite() && self.scale > 0.0) {
            return bad(format!("scale must be finite and > 0, got {}", self.scale));
        }
        if !self.mean.iter().all(|m| m.is_finite()) {
            return bad(format!("mean must be finite, got {:?}", self.mean));
        }
        if !self.std.iter().all(|s| s.is_finite() && *s > 0.0) {
            return bad(format!("std must be finite and > 0, got {:?}", self.std));
        }
        if self.intra_threads == 0 {
            return bad("intra_threads must be at least 1".into());
        }
        if self.metric && self.output_kind == OutputKind::Disparity {
            return bad(
                "a disparity output has no metric scale: say output_kind = \"depth\" or \
                 \"inverse_depth\" for a metric model"
                    .into(),
            );
        }
        if let Some(m) = self.multiple_of {
            if m == 0 {
                return bad("multiple_of must be at least 1".into());
            }
            if self.resize == ResizeMode::Stretch
                && (!self.input_width.is_multiple_of(m) || !self.input_height.is_multiple_of(m))
            {
                return bad(format!(
                    "input size {}x{} is not a multiple of {m}",
                    self.input_width, self.input_height
                ));
            }
        }
        Ok(())
    }

    /// Checks this config against the model's real inputs and outputs; the error names the
    /// first mismatch and lists what the model has.
    pub fn validate(&self, sig: &ModelSignature) -> Result<()> {
        self.check_values()?;
        let fail = |msg: String| {
            Err(Error::Prior(format!(
                "config `{}` does not fit the model: {msg} ({sig})",
                self.name
            )))
        };
        let Some(input) = sig.input(&self.input) else {
            return fail(format!("the model has no input `{}`", self.input));
        };
        if sig.inputs.len() != 1 {
            return fail(format!(
                "the model has {} inputs; only single-image models can be fed",
                sig.inputs.len()
            ));
        }
        if !input.is_f32 {
            return fail(format!("input `{}` is not float32", self.input));
        }
        let Some(shape) = input.shape.as_deref() else {
            return fail(format!("input `{}` is not a tensor", self.input));
        };
        if shape.len() != 4 {
            return fail(format!(
                "input `{}` has rank {}, expected 4",
                self.input,
                shape.len()
            ));
        }
        let (c, h, w) = match self.layout {
            Layout::Nchw => (shape[1], shape[2], shape[3]),
            Layout::Nhwc => (shape[3], shape[1], shape[2]),
        };
        let fits = |dim: i64, want: i64| dim < 0 || dim == want;
        if !fits(shape[0], 1) {
            return fail(format!(
                "input `{}` has batch size {}, expected 1",
                self.input, shape[0]
            ));
        }
        if !fits(c, 3) {
            return fail(format!(
                "input `{}` has {c} channels in {:?} layout, expected 3",
                self.input, self.layout
            ));
        }
        let dynamic = h < 0 && w < 0;
        match self.resize {
            ResizeMode::KeepAspect if !dynamic => {
                return fail(format!(
                    "resize = \"keep_aspect\" needs dynamic spatial dimensions, but input `{}` is \
                     fixed at {w}x{h}",
                    self.input
                ));
            }
            ResizeMode::Stretch
                if !fits(h, i64::from(self.input_height))
                    || !fits(w, i64::from(self.input_width)) =>
            {
                return fail(format!(
                    "config input size is {}x{} but input `{}` is {}x{} (width x height)",
                    self.input_width,
                    self.input_height,
                    self.input,
                    if w < 0 { "?".into() } else { w.to_string() },
                    if h < 0 { "?".into() } else { h.to_string() },
                ));
            }
            _ => {}
        }
        let Some(output) = sig.output(&self.output) else {
            return fail(format!("the model has no output `{}`", self.output));
        };
        if !output.is_f32 {
            return fail(format!("output `{}` is not float32", self.output));
        }
        match output.shape.as_deref() {
            Some(s) if (2..=4).contains(&s.len()) => Ok(()),
            Some(s) => fail(format!(
                "output `{}` has rank {}, expected 2 to 4",
                self.output,
                s.len()
            )),
            None => fail(format!("output `{}` is not a tensor", self.output)),
        }
    }
}

/// How a model's config was found.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Recognition {
    /// The file's sha256 is a known release.
    Sha256,
    /// Input/output names and shapes match a known model family.
    Signature,
    /// The user passed a config.
    UserConfig,
}

/// Known models, recognised from the ONNX file itself: first by sha256, then by the
/// names and shapes of its inputs and outputs (`file_name` disambiguates the one case where
/// shapes alone cannot: DPT-Hybrid vs other 384×384 MiDaS models). `None` means "unknown:
/// pass a config". Only FastDepth is metric: a model recognised by its shapes alone is never
/// taken for metric unless it is FastDepth's exact layout.
///
/// | model | how | input | normalisation | output |
/// |---|---|---|---|---|
/// | PyDNet++ stand-in (shared data) | sha256, or input `image` `[1,3,448,640]` + output `depth_half` | 640×448 | RGB/255 | `depth_half`, depth → 1/x |
/// | MiDaS v2.1 small, official `model-small.onnx` | sha256 | 256×256 | RGB/255 (mean/std are inside the released graph, see MiDaS `tf/make_onnx_model.py`) | first output, inverse depth |
/// | MiDaS v2.1 small, torch.hub export | one input `[1,3,256,256]`, one output | 256×256 | ImageNet mean/std | inverse depth |
/// | DPT-Hybrid 384 | one input `[1,3,384,384]`, one output, file name contains `dpt` | 384×384 | mean = std = 0.5 | inverse depth |
/// | FastDepth NYU (shared data) | sha256, or input `image` `[1,3,H,W]` (H, W multiples of 32 or dynamic) + output `depth` `[1,1,H,W]` | 224×224 | RGB/255 | `depth`, **metric** depth → 1/x |
/// | Depth Anything V2 (fabio-sim / onnx-community exports) | input `pixel_values` or `image`, output `predicted_depth` or `depth` | 518 (keep aspect, multiple of 14, when dynamic) | ImageNet mean/std | inverse depth |
pub fn recognise(
    sig: &ModelSignature,
    sha256: &str,
    file_name: &str,
) -> Option<(ModelConfig, Recognition)> {
    if let Some(config) = recognise_by_hash(sig, sha256) {
        return Some((config, Recognition::Sha256));
    }
    recognise_by_signature(sig, file_name).map(|config| (config, Recognition::Signature))
}

/// The defaults of a model config: the signature's first input, stretched to `w × h`, RGB/255
/// with no mean/std, one output of `kind`.
fn base_config(
    input: &str,
    name: &str,
    (w, h): (u32, u32),
    output: &str,
    kind: OutputKind,
) -> ModelConfig {
    ModelConfig {
        name: name.into(),
        input: input.into(),
        input_width: w,
        input_height: h,
        multiple_of: None,
        layout: Layout::Nchw,
        scale: default_scale(),
        mean: default_mean(),
        std: default_std(),
        output: output.into(),
        output_kind: kind,
        metric: false,
        resize: ResizeMode::Stretch,
        intra_threads: default_threads(),
    }
}

fn pydnet_config(input: &str) -> ModelConfig {
    base_config(
        input,
        "pydnet_pp_matterport_448x640",
        (640, 448),
        "depth_half",
        OutputKind::Depth,
    )
}

/// FastDepth (Wofk et al. ICRA 2019, NYU Depth v2): RGB/255 stretched to 224×224 (other
/// sizes are worse, shared data README §5), output `depth` in metres.
fn fastdepth_config(input: &str, output: &str) -> ModelConfig {
    let mut config = base_config(
        input,
        "fastdepth_nyu_224",
        (224, 224),
        output,
        OutputKind::Depth,
    );
    config.metric = true;
    config
}

/// The released files recognised by their hash.
fn recognise_by_hash(sig: &ModelSignature, sha256: &str) -> Option<ModelConfig> {
    let input = &sig.inputs.first()?.name;
    let first_output = &sig.outputs.first()?.name;
    if sha256.eq_ignore_ascii_case(PYDNET_PP_SHA256) {
        return Some(pydnet_config(input));
    }
    if sha256.eq_ignore_ascii_case(FASTDEPTH_NYU_SHA256) {
        return Some(fastdepth_config(input, first_output));
    }
    if sha256.eq_ignore_ascii_case(MIDAS_V21_SMALL_RELEASE_SHA256) {
        return Some(base_config(
            input,
            "midas_v21_small_256",
            (256, 256),
            first_output,
            OutputKind::InverseDepth,
        ));
    }
    None
}

/// The exports recognised by their inputs, outputs and shapes (and DPT by its file name).
fn recognise_by_signature(sig: &ModelSignature, file_name: &str) -> Option<ModelConfig> {
    let first_input = sig.inputs.first()?;
    let first_output = &sig.outputs.first()?.name;
    let input = &first_input.name;
    let input_shape = first_input.shape.as_deref().unwrap_or(&[]);
    let has_output = |n: &str| sig.output(n).is_some();
    if input == "image" && input_shape == [1, 3, 448, 640] && has_output("depth_half") {
        return Some(pydnet_config(input));
    }
    let single = sig.inputs.len() == 1 && sig.outputs.len() == 1;
    // FastDepth's `depth` keeps a channel axis (`[1, 1, H, W]`); Depth Anything's exports drop
    // it (`[N, H, W]`), so the rank tells the two `image` → `depth` models apart.
    let output_shape = sig.outputs.first()?.shape.as_deref().unwrap_or(&[]);
    if single
        && input == "image"
        && has_output("depth")
        && output_shape.len() == 4
        && output_shape[1] == 1
        && input_shape.len() == 4
        && input_shape[2..].iter().all(|&d| d < 0 || d % 32 == 0)
    {
        return Some(fastdepth_config(input, "depth"));
    }
    let da_output = ["predicted_depth", "depth"]
        .into_iter()
        .find(|n| has_output(n));
    if single
        && matches!(input.as_str(), "pixel_values" | "image")
        && let Some(output) = da_output
        && input_shape.len() == 4
    {
        return depth_anything_config(input, output, (input_shape[2], input_shape[3]));
    }
    let (name, side, mean, std) = if single && input_shape == [1, 3, 256, 256] {
        ("midas_v21_small_256", 256, IMAGENET_MEAN, IMAGENET_STD)
    } else if single
        && input_shape == [1, 3, 384, 384]
        && file_name.to_ascii_lowercase().contains("dpt")
    {
        ("dpt_hybrid_384", 384, [0.5; 3], [0.5; 3])
    } else {
        return None;
    };
    let mut config = base_config(
        input,
        name,
        (side, side),
        first_output,
        OutputKind::InverseDepth,
    );
    config.mean = mean;
    config.std = std;
    Some(config)
}

/// Depth Anything V2 at its input's fixed size (`h × w`, multiples of 14, else not this
/// model), or at 518 keeping the aspect when the size is dynamic.
fn depth_anything_config(input: &str, output: &str, (h, w): (i64, i64)) -> Option<ModelConfig> {
    let name = "depth_anything_v2";
    let mut config = if h > 0 && w > 0 {
        if h % 14 != 0 || w % 14 != 0 {
            return None;
        }
        base_config(
            input,
            name,
            (w as u32, h as u32),
            output,
            OutputKind::InverseDepth,
        )
    } else {
        let mut c = base_config(input, name, (518, 518), output, OutputKind::InverseDepth);
        c.resize = ResizeMode::KeepAspect;
        c
    };
    config.multiple_of = Some(14);
    config.mean = IMAGENET_MEAN;
    config.std = IMAGENET_STD;
    Some(config)
}

#[cfg(test)]
#[path = "model_config_tests.rs"]
mod tests;
