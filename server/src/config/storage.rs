//! `[storage]`: where uploads, session metadata, results and saved maps live. The local
//! filesystem below `data_dir` by default; an S3-compatible bucket for a cluster, whose nodes
//! then share every session's data (placement of uploads, failover).

use serde::{Deserialize, Serialize};

/// The store backend.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StorageBackend {
    /// Files below `data_dir` (fsynced; one node's own).
    #[default]
    Fs,
    /// An S3-compatible bucket (`[storage.s3]`), through the `object_store` crate; shared by
    /// every node that names it.
    S3,
}

/// `[storage]`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StorageConfig {
    /// `"fs"` (default) or `"s3"` (`RELFUSIOND_STORAGE`).
    pub backend: StorageBackend,
    pub s3: S3Config,
}

/// `[storage.s3]`: an S3-compatible endpoint. Credentials are best left to the environment
/// (`AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`), which fills what the file leaves empty.
#[derive(Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct S3Config {
    /// `https://s3.eu-west-1.amazonaws.com`, `http://minio:9000`, ... (`RELFUSIOND_S3_ENDPOINT`).
    pub endpoint: String,
    /// The bucket (`RELFUSIOND_S3_BUCKET`); it must exist.
    pub bucket: String,
    pub region: String,
    /// Every key of this service below this prefix (several deployments in one bucket).
    pub prefix: String,
    pub access_key_id: String,
    pub secret_access_key: String,
    /// Plain `http://` endpoints are refused unless this is set (a test server, a private
    /// network).
    pub allow_http: bool,
    /// Each request's deadline, seconds.
    pub timeout_s: u64,
}

impl Default for S3Config {
    fn default() -> Self {
        Self {
            endpoint: String::new(),
            bucket: String::new(),
            region: "us-east-1".into(),
            prefix: String::new(),
            access_key_id: String::new(),
            secret_access_key: String::new(),
            allow_http: false,
            timeout_s: 30,
        }
    }
}

/// The secret stays out of logs and `--print-config`-like debug output.
impl std::fmt::Debug for S3Config {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("S3Config")
            .field("endpoint", &self.endpoint)
            .field("bucket", &self.bucket)
            .field("region", &self.region)
            .field("prefix", &self.prefix)
            .field("access_key_id", &self.access_key_id)
            .field("allow_http", &self.allow_http)
            .field("timeout_s", &self.timeout_s)
            .finish_non_exhaustive()
    }
}

impl StorageConfig {
    /// Applies `RELFUSIOND_STORAGE`, `RELFUSIOND_S3_ENDPOINT`, `RELFUSIOND_S3_BUCKET`,
    /// `RELFUSIOND_S3_PREFIX` and, where the file leaves them empty, `AWS_ACCESS_KEY_ID`,
    /// `AWS_SECRET_ACCESS_KEY` and `AWS_REGION`.
    pub fn apply_env(&mut self, env: &impl Fn(&str) -> Option<String>) -> Result<(), String> {
        if let Some(v) = env("RELFUSIOND_STORAGE") {
            self.backend = match v.trim() {
                "fs" => StorageBackend::Fs,
                "s3" => StorageBackend::S3,
                other => return Err(format!("$RELFUSIOND_STORAGE: {other:?}: fs or s3")),
            };
        }
        let s3 = &mut self.s3;
        for (var, field) in [
            ("RELFUSIOND_S3_ENDPOINT", &mut s3.endpoint),
            ("RELFUSIOND_S3_BUCKET", &mut s3.bucket),
            ("RELFUSIOND_S3_PREFIX", &mut s3.prefix),
        ] {
            if let Some(v) = env(var) {
                *field = v.trim().to_string();
            }
        }
        for (var, field) in [
            ("AWS_ACCESS_KEY_ID", &mut s3.access_key_id),
            ("AWS_SECRET_ACCESS_KEY", &mut s3.secret_access_key),
            ("AWS_REGION", &mut s3.region),
        ] {
            if field.is_empty()
                && let Some(v) = env(var)
            {
                *field = v.trim().to_string();
            }
        }
        Ok(())
    }

    /// What serde cannot check.
    pub fn validate(&self) -> Result<(), String> {
        if self.backend != StorageBackend::S3 {
            return Ok(());
        }
        let s3 = &self.s3;
        if s3.endpoint.is_empty() || s3.bucket.is_empty() {
            return Err(
                "storage.s3: endpoint and bucket are required with backend = \"s3\"".into(),
            );
        }
        if s3.endpoint.starts_with("http://") && !s3.allow_http {
            return Err(format!(
                "storage.s3.endpoint {:?} is plain HTTP: use https:// or set allow_http",
                s3.endpoint
            ));
        }
        if !s3.endpoint.starts_with("http://") && !s3.endpoint.starts_with("https://") {
            return Err(format!(
                "storage.s3.endpoint {:?}: an http(s):// URL",
                s3.endpoint
            ));
        }
        if s3.prefix.split('/').any(|c| c == ".." || c == ".") || s3.prefix.starts_with('/') {
            return Err(format!(
                "storage.s3.prefix {:?}: a relative key prefix",
                s3.prefix
            ));
        }
        if s3.timeout_s == 0 {
            return Err("storage.s3.timeout_s must be positive".into());
        }
        Ok(())
    }
}
