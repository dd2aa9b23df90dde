//! Off backend (to be implemented).

use std::path::Path;

use super::{Extras, IoError, Sink, Source, SourceInfo};
use crate::points::PointBatch;

/// Off header information a sink reproduces.
#[derive(Debug, Clone, Default)]
pub struct OffMeta {}

/// Off content besides the points.
#[derive(Debug, Clone, Default)]
pub struct OffTrailer {}

/// Streaming Off reader.
pub struct OffSource {
    info: SourceInfo,
}

impl OffSource {
    /// Opens a file.
    ///
    /// # Errors
    /// Always, until implemented.
    pub fn open(path: &Path) -> Result<OffSource, IoError> {
        Err(IoError::Unsupported {
            path: path.to_path_buf(),
            detail: "not implemented".into(),
        })
    }
}

impl Source for OffSource {
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

/// Streaming Off writer.
pub struct OffSink {}

impl OffSink {
    /// Creates a sink.
    ///
    /// # Errors
    /// Always, until implemented.
    pub fn create(path: &Path, _like: &SourceInfo, _count: u64) -> Result<OffSink, IoError> {
        Err(IoError::Unsupported {
            path: path.to_path_buf(),
            detail: "not implemented".into(),
        })
    }
}

impl Sink for OffSink {
    fn write_batch(&mut self, _batch: &PointBatch) -> Result<(), IoError> {
        Ok(())
    }
    fn finish(self: Box<Self>, _extras: &Extras) -> Result<(), IoError> {
        Ok(())
    }
}
