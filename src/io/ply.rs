//! Ply backend (to be implemented).

use std::path::Path;

use super::{Extras, IoError, Sink, Source, SourceInfo};
use crate::points::PointBatch;

/// Ply header information a sink reproduces.
#[derive(Debug, Clone, Default)]
pub struct PlyMeta {}

/// Ply content besides the points.
#[derive(Debug, Clone, Default)]
pub struct PlyTrailer {}

/// Streaming Ply reader.
pub struct PlySource {
    info: SourceInfo,
}

impl PlySource {
    /// Opens a file.
    ///
    /// # Errors
    /// Always, until implemented.
    pub fn open(path: &Path) -> Result<PlySource, IoError> {
        Err(IoError::Unsupported {
            path: path.to_path_buf(),
            detail: "not implemented".into(),
        })
    }
}

impl Source for PlySource {
    fn info(&self) -> &SourceInfo {
        &self.info
    }
    fn read_batch(&mut self, _batch: &mut PointBatch, _max: usize) -> Result<usize, IoError> {
        Ok(0)
    }
    fn finish(self: Box<Self>) -> Result<Extras, IoError> {
        Ok(Extras::default())
    }
}

/// Streaming Ply writer.
pub struct PlySink {}

impl PlySink {
    /// Creates a sink.
    ///
    /// # Errors
    /// Always, until implemented.
    pub fn create(path: &Path, _like: &SourceInfo, _count: u64) -> Result<PlySink, IoError> {
        Err(IoError::Unsupported {
            path: path.to_path_buf(),
            detail: "not implemented".into(),
        })
    }
}

impl Sink for PlySink {
    fn write_batch(&mut self, _batch: &PointBatch) -> Result<(), IoError> {
        Ok(())
    }
    fn finish(self: Box<Self>, _extras: &Extras) -> Result<(), IoError> {
        Ok(())
    }
}
