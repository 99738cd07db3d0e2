//! The durable upload path: an archive becomes a stored, acknowledged session, run on this
//! node or — with a shared store — on the node cluster placement chose.

use super::*;

/// An upload as the HTTP layer received it.
#[derive(Debug)]
pub struct NewUpload<'a> {
    /// The archive, in [`SessionManager::temp_dir`].
    pub archive: &'a Path,
    pub kind: ArchiveKind,
    /// The given intrinsics, if any.
    pub camera: Option<PinholeCamera>,
    pub config: SlamConfig,
}

impl SessionManager {
    /// Accepts an uploaded dataset: extracts the archive safely (400 for traversal, links,
    /// a broken archive or no TUM layout; 413 for more than the limits allow, zip bombs
    /// included), resolves the camera (the given one, else `calibration.txt`, else a TUM
    /// preset from the folder name; 400 without any, or one too large for this server),
    /// stores it durably, and only then returns (the acknowledgement). Processing starts on
    /// the pool when a slot is free.
    pub async fn create_upload(
        &self,
        ticket: UploadTicket,
        upload: NewUpload<'_>,
    ) -> Result<Arc<Session>, ApiError> {
        let (meta, max_keyframes) = self.store_upload(&ticket, upload, None).await?;
        let id = meta.id.clone();
        let session = Arc::new(self.build(meta, max_keyframes));
        let start = ticket.redeem(|admission| {
            self.write_sessions().insert(id, session.clone());
            self.queue_or_slot(admission, &session)
        });
        if start {
            self.start_or_release(&session, self.model.clone());
        }
        Ok(session)
    }

    /// Accepts an uploaded dataset as [`Self::create_upload`] does, for `node` to run: the
    /// stored metadata names that node, and this one neither holds nor starts it. The caller
    /// then hands it over ([`crate::cluster::Cluster::hand_off`]), or takes it back with
    /// [`Self::take_over`] when `node` does not answer. Shared stores only.
    pub async fn create_upload_for(
        &self,
        node: &str,
        ticket: UploadTicket,
        upload: NewUpload<'_>,
    ) -> Result<SessionInfo, ApiError> {
        if !self.store.shared() {
            return Err(ApiError::internal(
                "an upload can be handed to another node only through a shared store",
            ));
        }
        let (meta, _) = self.store_upload(&ticket, upload, Some(node)).await?;
        Ok(meta.info())
    }

    /// Whether other nodes read and write the same store (uploads may then run elsewhere).
    pub fn shares_store(&self) -> bool {
        self.store.shared()
    }

    /// Extracts, checks and stores an upload, then its metadata (naming `node`, else this
    /// one): once this returns, the upload is acknowledged and survives any crash.
    async fn store_upload(
        &self,
        ticket: &UploadTicket,
        upload: NewUpload<'_>,
        node: Option<&str>,
    ) -> Result<(SessionMeta, usize), ApiError> {
        self.refuse_if_shutting_down()?;
        let model = self.resolve_model(None)?;
        let id = new_id();
        // A filesystem store extracts in place; any other store gets the extracted tree
        // copied in (`folders::store`), one object per file, before the acknowledgement.
        let staging = self
            .store
            .local_path(&format!("sessions/{id}/upload.partial"))
            .unwrap_or_else(|| std::env::temp_dir().join(format!("relfusiond-{id}.partial")));
        let limits = ExtractLimits::for_archive(&self.config.limits, upload.archive)?;
        let NewUpload {
            archive,
            kind,
            camera,
            config: slam_config,
        } = upload;
        let slam_config = self.with_operator_settings(slam_config, None);
        let archive = archive.to_path_buf();
        let manager = self
            .me
            .upgrade()
            .ok_or_else(|| ApiError::unavailable("the server is shutting down"))?;
        let checked_config = slam_config.clone();
        let key = upload_key(&id);
        let extracted = tokio::task::spawn_blocking(move || {
            let check = |c: &PinholeCamera| manager.map_limit(c, &checked_config).map(|_| ());
            let mut staged = None;
            let stored = crate::folders::store(manager.store.as_ref(), &key, |final_dir| {
                let result =
                    stage_upload(&archive, kind, &staging, final_dir, limits, camera, &check);
                let failed = result.is_err();
                staged = Some(result);
                if failed { Err(String::new()) } else { Ok(()) }
            });
            let _ = std::fs::remove_dir_all(&staging);
            match (staged, stored) {
                (Some(Err(e)), _) => Err(e),
                (Some(Ok(staged)), Ok(_)) => Ok(staged),
                (_, Err(e)) => Err(ApiError::internal(format!("storing the upload: {e}"))),
                (None, Ok(_)) => Err(ApiError::internal("the upload was not staged")),
            }
        })
        .await
        .map_err(|e| ApiError::internal(format!("extraction task failed: {e}")));
        let staged = extracted.and_then(|r| r).and_then(|staged| {
            let max_keyframes = self.map_limit(&staged.camera, &slam_config)?;
            Ok((staged, max_keyframes))
        });
        let (staged, max_keyframes) = match staged {
            Ok(v) => v,
            Err(e) => {
                let _ = self.store.delete_prefix(&session_prefix(&id));
                return Err(e);
            }
        };
        let mut dataset = String::from("upload");
        for part in staged.dataset_rel.components() {
            dataset.push('/');
            dataset.push_str(&part.as_os_str().to_string_lossy());
        }
        let meta = SessionMeta {
            version: META_VERSION,
            id: id.clone(),
            owner: ticket.owner().clone(),
            kind: SessionKind::Upload,
            state: SessionState::Queued,
            camera: staged.camera,
            config: slam_config,
            model: model
                .as_ref()
                .map_or("none".into(), |m| m.name().to_string()),
            policy: FramePolicy::Wait,
            created_unix: now_unix(),
            error: None,
            dataset: Some(dataset),
            total_frames: Some(staged.frames as u64),
            counters: Default::default(),
            ended_unix: None,
            notice: None,
            upload_bytes: staged.bytes,
            results_bytes: 0,
            map: None,
            node: Some(node.unwrap_or(self.node()).to_string()),
            scale: None,
        };
        // The acknowledgement point: once meta.json is durable, the upload exists.
        if let Err(e) = meta.save(self.store.as_ref()) {
            let _ = self.store.delete_prefix(&session_prefix(&id));
            return Err(ApiError::internal(format!("storing the upload: {e}")));
        }
        Ok((meta, max_keyframes))
    }
}
