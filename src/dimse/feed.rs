//! The node as a front door of the application: every series it completes goes to
//! [`App::receive_series`], which assembles and records it exactly like an uploaded one (or nothing, when
//! it was sent again unchanged) and keeps its instances in the instance index that C-FIND and C-MOVE answer
//! from.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use tracing::Instrument as _;

use super::node::{DicomNode, NodeError};
use super::tracker::CompletedSeries;
use crate::app::{App, AppError};
use crate::dicom::UploadFile;

/// Start the delivery worker of `app` (sending through [`super::scu`]) and, when its settings give it a
/// port, the DICOM node, feeding complete series to the application; returns the node's address. The node runs as long as the runtime.
pub async fn serve_node(app: App) -> Result<Option<SocketAddr>, NodeError> {
    // Deliveries go out whether or not the node listens.
    app.start_deliveries(std::sync::Arc::new(super::sender::ScuCaller::new(
        &app.settings.dicom,
    )));
    // Derived results are indexed (QIDO-RS, WADO-RS), and series received by STOW-RS assembled once
    // stable, whether or not the node listens.
    app.spawn_result_indexer();
    app.spawn_stow_assembly();
    if app.settings.dicom.port.is_none() {
        return Ok(None);
    }
    let mut node = DicomNode::start_with(
        &app.settings.dicom,
        &app.settings.data_dir,
        Some(app.clone()),
    )
    .await?;
    // Volume jobs may pull their series from a PACS through this node.
    app.engine
        .install_puller(std::sync::Arc::new(super::puller::NodePuller::new(
            app.clone(),
            node.tracker(),
        )));
    let addr = node.local_addr();
    tokio::spawn(async move {
        while let Some(done) = node.next_completed().await {
            let span = tracing::info_span!("received_series", series_uid = %done.series_uid, calling_ae = %done.calling_ae);
            assemble(&app, done).instrument(span).await;
        }
    });
    Ok(Some(addr))
}

pub(super) fn instance_files(folder: &Path) -> std::io::Result<Vec<UploadFile>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(folder)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "dcm"))
        .collect();
    files.sort();
    Ok(files
        .into_iter()
        .map(|path| UploadFile {
            label: path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            path,
        })
        .collect())
}

/// Assemble one complete series; its folder is removed once the outcome is recorded (kept for the next
/// start when the database or storage failed).
async fn assemble(app: &App, done: CompletedSeries) {
    let folder = done.folder.clone();
    let listed = {
        let f = folder.clone();
        tokio::task::spawn_blocking(move || instance_files(&f)).await
    };
    let files = match listed {
        Ok(Ok(files)) => files,
        Ok(Err(e)) => {
            tracing::error!(error = %e, folder = %folder.display(), "cannot list a received series");
            return;
        }
        Err(e) => {
            tracing::error!(error = %e, "listing a received series failed");
            return;
        }
    };
    let keep = match app
        .receive_series(&done.series_uid, files, Some(done.calling_ae.as_str()))
        .await
    {
        Ok(Some(r)) => {
            let ready = r.ingested.ready().count();
            tracing::info!(upload_id = %r.upload_id, series_uid = %done.series_uid, instances = done.instances, ready, refused = r.ingested.series.len() - ready, "received series recorded");
            false
        }
        Ok(None) => false,
        Err(AppError::Refused(p)) => {
            tracing::warn!(series_uid = %done.series_uid, code = p.code.code(), detail = %p.detail, "received series refused");
            false
        }
        Err(e) => {
            tracing::error!(series_uid = %done.series_uid, error = %e, "received series not recorded; kept for the next start");
            true
        }
    };
    if !keep {
        let _ = tokio::fs::remove_dir_all(&folder).await;
    }
}
