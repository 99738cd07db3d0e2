//! The depth model shared by every session, run on the GPU pool.
//!
//! The model is loaded once at start ([`SharedModel::load`]): an ONNX session is large, and one
//! copy per session would multiply the memory and the load time. Each session's pipeline gets a
//! [`PooledPrior`], whose `predict` runs the inference as a job of that session on the
//! [`crate::gpu_pool::GpuPool`], so keyframes of different sessions take turns on the
//! accelerator.

use std::sync::{Arc, Mutex};
use std::time::Instant;

use relfusion_slam::dense::{DepthPrior, InverseDepth, ModelConfig, OnnxDepthPrior};

use crate::ServerError;
use crate::config::ModelSettings;
use crate::gpu_pool::PoolClient;
use crate::metrics::{Metrics, Stage};

/// A loaded depth model and the name sessions know it by.
#[derive(Clone)]
pub struct SharedModel {
    name: String,
    prior: Arc<Mutex<Box<dyn DepthPrior>>>,
    config: ModelConfig,
}

impl std::fmt::Debug for SharedModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SharedModel")
            .field("name", &self.name)
            .finish()
    }
}

impl SharedModel {
    /// Wraps any prior (tests, future model kinds).
    pub fn new(name: impl Into<String>, prior: Box<dyn DepthPrior>) -> Self {
        let config = prior.describe().clone();
        Self {
            name: name.into(),
            prior: Arc::new(Mutex::new(prior)),
            config,
        }
    }

    /// Loads the configured model; `None` when none is configured.
    pub fn load(settings: &ModelSettings) -> Result<Option<Self>, ServerError> {
        if !settings.is_set() {
            return Ok(None);
        }
        let err = |message: String| ServerError::Model {
            path: settings.path.display().to_string(),
            message,
        };
        let model_config = if settings.config.as_os_str().is_empty() {
            None
        } else {
            Some(ModelConfig::from_file(&settings.config).map_err(|e| err(e.to_string()))?)
        };
        let prior =
            OnnxDepthPrior::load(&settings.path, model_config).map_err(|e| err(e.to_string()))?;
        Ok(Some(Self::new(settings.name(), Box::new(prior))))
    }

    /// The model's name (`model` in session info).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// A prior for one session's pipeline, running on `client`'s share of the pool.
    pub fn pooled(&self, client: Arc<PoolClient>, metrics: Arc<Metrics>) -> PooledPrior {
        PooledPrior {
            model: self.clone(),
            client,
            metrics,
        }
    }
}

/// A session's view of the shared model: each prediction is a GPU-pool job of the session.
#[derive(Debug)]
pub struct PooledPrior {
    model: SharedModel,
    client: Arc<PoolClient>,
    metrics: Arc<Metrics>,
}

impl DepthPrior for PooledPrior {
    fn predict(&mut self, rgb: &::image::RgbImage) -> relfusion_slam::Result<InverseDepth> {
        let start = Instant::now();
        let prior = self.model.prior.clone();
        let rgb = rgb.clone();
        let result = self.client.run(move || {
            prior
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .predict(&rgb)
        });
        self.metrics
            .observe_stage(Stage::Prior, start.elapsed().as_secs_f64());
        result.map_err(|e| relfusion_slam::Error::Prior(e.to_string()))?
    }

    fn describe(&self) -> &ModelConfig {
        &self.model.config
    }
}
