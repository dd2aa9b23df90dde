//! Obj backend (to be implemented).

use std::path::Path;

use super::{Extras, IoError, Sink, Source, SourceInfo};
use crate::points::PointBatch;

/// Obj header information a sink reproduces.
#[derive(Debug, Clone, Default)]
pub struct ObjMeta {}

/// Obj content besides the points.
#[derive(Debug, Clone, Default)]
pub struct ObjTrailer {}

/// Streaming Obj reader.
pub struct ObjSource {
    info: SourceInfo,
}

impl ObjSource {
    /// Opens a file.
    ///
    /// # Errors
    /// Always, until implemented.
    pub fn open(path: &Path) -> Result<ObjSource, IoError> {
        Err(IoError::Unsupported {
            path: path.to_path_buf(),
            detail: "not implemented".into(),
        })
    }
}

impl Source for ObjSource {
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

/// Streaming Obj writer.
pub struct ObjSink {}

impl ObjSink {
    /// Creates a sink.
    ///
    /// # Errors
    /// Always, until implemented.
    pub fn create(path: &Path, _like: &SourceInfo, _count: u64) -> Result<ObjSink, IoError> {
        Err(IoError::Unsupported {
            path: path.to_path_buf(),
            detail: "not implemented".into(),
        })
    }
}

impl Sink for ObjSink {
    fn write_batch(&mut self, _batch: &PointBatch) -> Result<(), IoError> {
        Ok(())
    }
    fn finish(self: Box<Self>, _extras: &Extras) -> Result<(), IoError> {
        Ok(())
    }
}
