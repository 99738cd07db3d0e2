//! [`S3Store`]: the store in an S3-compatible bucket through the `object_store` crate, shared
//! by every node of a cluster.
//!
//! The store interface is blocking (sessions' threads call it); the crate is async. Requests
//! run on the store's own small runtime and the caller waits for the answer on a channel, which
//! works from any thread, a Tokio worker included (no runtime is entered twice). Each request
//! has a deadline (`storage.s3.timeout_s`, plus the crate's retries).
//!
//! S3 gives what the store promises: a PUT is atomic (readers see the old object or the whole
//! new one) and durable once acknowledged.

use std::sync::Arc;
use std::time::Duration;

use futures_util::{StreamExt, TryStreamExt};
use object_store::aws::AmazonS3Builder;
use object_store::path::Path as KeyPath;
use object_store::{ClientOptions, ObjectStore as _, PutPayload, RetryConfig};

use super::{ObjectStore, StoreError, check_key};
use crate::config::S3Config;

/// The store in one bucket, below `prefix`.
pub struct S3Store {
    inner: Arc<dyn object_store::ObjectStore>,
    /// `""` or `"prefix/"`.
    prefix: String,
    describe: String,
    runtime: Option<tokio::runtime::Runtime>,
    deadline: Duration,
}

impl std::fmt::Debug for S3Store {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("S3Store")
            .field("bucket", &self.describe)
            .finish_non_exhaustive()
    }
}

fn remote(what: &str, e: impl std::fmt::Display) -> StoreError {
    StoreError::Remote(format!("{what}: {e}"))
}

impl S3Store {
    /// Connects to the bucket of `config` and checks that it answers (a listing), so that a
    /// wrong endpoint or credential stops the node at start, not at the first upload.
    pub fn open(config: &S3Config) -> Result<Self, StoreError> {
        let timeout = Duration::from_secs(config.timeout_s);
        let store = AmazonS3Builder::new()
            .with_endpoint(&config.endpoint)
            .with_bucket_name(&config.bucket)
            .with_region(&config.region)
            .with_access_key_id(&config.access_key_id)
            .with_secret_access_key(&config.secret_access_key)
            .with_allow_http(config.allow_http)
            .with_virtual_hosted_style_request(false)
            .with_client_options(
                ClientOptions::new()
                    .with_timeout(timeout)
                    .with_connect_timeout(Duration::from_secs(5))
                    .with_allow_http(config.allow_http),
            )
            .with_retry(RetryConfig {
                max_retries: 3,
                retry_timeout: timeout,
                ..RetryConfig::default()
            })
            .build()
            .map_err(|e| remote("configuring the S3 store", e))?;
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("s3-store")
            .enable_all()
            .build()
            .map_err(|e| remote("the S3 store's runtime", e))?;
        let prefix = match config.prefix.trim_matches('/') {
            "" => String::new(),
            p => format!("{p}/"),
        };
        let s3 = Self {
            inner: Arc::new(store),
            prefix,
            describe: format!("{}/{}", config.endpoint, config.bucket),
            runtime: Some(runtime),
            // Retries included: three tries of one timeout each, and their back-off.
            deadline: timeout * 4 + Duration::from_secs(5),
        };
        s3.list("health/")?;
        Ok(s3)
    }

    /// Runs `work` on the store's runtime and waits for it (with the deadline).
    fn block<T: Send + 'static>(
        &self,
        what: &str,
        work: impl std::future::Future<Output = Result<T, StoreError>> + Send + 'static,
    ) -> Result<T, StoreError> {
        let runtime = self
            .runtime
            .as_ref()
            .ok_or_else(|| remote(what, "the store is closed"))?;
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        runtime.spawn(async move {
            let _ = tx.send(work.await);
        });
        rx.recv_timeout(self.deadline)
            .map_err(|_| remote(what, format!("no answer within {:?}", self.deadline)))?
    }

    fn path(&self, key: &str) -> Result<KeyPath, StoreError> {
        check_key(key)?;
        KeyPath::parse(format!("{}{key}", self.prefix))
            .map_err(|_| StoreError::BadKey(key.to_string()))
    }

    /// Every key below the folder `folder` (`""`: all), without the store's prefix.
    fn list_folder(&self, folder: &str) -> Result<Vec<String>, StoreError> {
        let location = format!("{}{}", self.prefix, folder.trim_end_matches('/'));
        let location = location.trim_end_matches('/').to_string();
        let inner = self.inner.clone();
        let prefix = self.prefix.clone();
        let what = format!("listing {}{folder}", self.prefix);
        self.block(&what.clone(), async move {
            let path = (!location.is_empty())
                .then(|| KeyPath::parse(&location))
                .transpose()
                .map_err(|e| remote(&what, e))?;
            let metas: Vec<_> = inner
                .list(path.as_ref())
                .map_err(|e| remote(&what, e))
                .try_collect()
                .await?;
            Ok(metas
                .into_iter()
                .filter_map(|m| m.location.as_ref().strip_prefix(&prefix).map(String::from))
                .collect())
        })
    }
}

impl Drop for S3Store {
    fn drop(&mut self) {
        // May run inside another runtime, where a blocking shutdown would panic.
        if let Some(runtime) = self.runtime.take() {
            runtime.shutdown_background();
        }
    }
}

impl ObjectStore for S3Store {
    fn put(&self, key: &str, bytes: &[u8]) -> Result<(), StoreError> {
        let path = self.path(key)?;
        let inner = self.inner.clone();
        let payload = PutPayload::from(bytes.to_vec());
        let what = format!("storing {key}");
        self.block(&what.clone(), async move {
            inner
                .put(&path, payload)
                .await
                .map(|_| ())
                .map_err(|e| remote(&what, e))
        })
    }

    fn get(&self, key: &str) -> Result<Option<Vec<u8>>, StoreError> {
        let path = self.path(key)?;
        let inner = self.inner.clone();
        let what = format!("reading {key}");
        self.block(&what.clone(), async move {
            match inner.get(&path).await {
                Ok(result) => result
                    .bytes()
                    .await
                    .map(|b| Some(b.to_vec()))
                    .map_err(|e| remote(&what, e)),
                Err(object_store::Error::NotFound { .. }) => Ok(None),
                Err(e) => Err(remote(&what, e)),
            }
        })
    }

    fn list(&self, prefix: &str) -> Result<Vec<String>, StoreError> {
        let folder = prefix.rfind('/').map_or("", |i| &prefix[..i]);
        if !folder.is_empty() {
            check_key(folder)?;
        }
        let mut keys: Vec<String> = self
            .list_folder(folder)?
            .into_iter()
            .filter(|k| k.starts_with(prefix))
            .collect();
        keys.sort();
        Ok(keys)
    }

    fn delete_prefix(&self, prefix: &str) -> Result<(), StoreError> {
        let trimmed = prefix.trim_end_matches('/');
        check_key(trimmed)?;
        let mut keys = self.list(&format!("{trimmed}/"))?;
        if !prefix.ends_with('/') {
            keys.push(trimmed.to_string());
        }
        let paths = keys
            .iter()
            .map(|k| self.path(k))
            .collect::<Result<Vec<_>, _>>()?;
        let inner = self.inner.clone();
        let what = format!("deleting {prefix}");
        self.block(&what.clone(), async move {
            let stream = futures_util::stream::iter(paths.into_iter().map(Ok)).boxed();
            let results: Vec<_> = inner.delete_stream(stream).collect().await;
            for result in results {
                match result {
                    Ok(_) | Err(object_store::Error::NotFound { .. }) => {}
                    Err(e) => return Err(remote(&what, e)),
                }
            }
            Ok(())
        })
    }

    fn local_path(&self, _key: &str) -> Option<std::path::PathBuf> {
        None
    }

    fn shared(&self) -> bool {
        true
    }
}
