//! What every sink checks of what it is given: that a batch carries records of the layout the
//! sink was created for ([`check_batch`]) and that the points written match the count it
//! announced ([`Tally`]).

use std::path::Path;

use super::IoError;
use crate::points::{PointBatch, Schema};

/// Checks that a batch carries records of the announced layout.
pub(crate) fn check_batch(path: &Path, schema: &Schema, batch: &PointBatch) -> Result<(), IoError> {
    if batch.record_len != schema.record_len
        || batch.records.len() != batch.len() * schema.record_len
    {
        return Err(IoError::invalid(
            path,
            format!(
                "a batch of {} points carries {} record bytes of {} each, but the sink was created \
                 for {}-byte records",
                batch.len(),
                batch.records.len(),
                batch.record_len,
                schema.record_len
            ),
        ));
    }
    Ok(())
}

/// Counts the points a sink writes against the count it announced.
pub(crate) struct Tally {
    announced: u64,
    written: u64,
}

impl Tally {
    pub(crate) fn new(announced: u64) -> Tally {
        Tally {
            announced,
            written: 0,
        }
    }

    /// Points written so far.
    pub(crate) fn written(&self) -> u64 {
        self.written
    }

    /// Accounts for `n` more points; errors when they exceed the announced count.
    pub(crate) fn add(&mut self, path: &Path, n: usize) -> Result<(), IoError> {
        let total = self.written + n as u64;
        if total > self.announced {
            return Err(IoError::invalid(
                path,
                format!(
                    "got {total} points to write but {} were announced",
                    self.announced
                ),
            ));
        }
        self.written = total;
        Ok(())
    }

    /// Accounts for the points of an appended body ([`super::Sink::append_body`]).
    pub(crate) fn add_body(
        &mut self,
        path: &Path,
        stats: &super::BodyStats,
    ) -> Result<(), IoError> {
        let n = usize::try_from(stats.points).unwrap_or(usize::MAX);
        self.add(path, n)
    }

    /// Errors unless exactly the announced number of points was written.
    pub(crate) fn check(&self, path: &Path) -> Result<(), IoError> {
        if self.written != self.announced {
            return Err(IoError::invalid(
                path,
                format!(
                    "wrote {} points but {} were announced",
                    self.written, self.announced
                ),
            ));
        }
        Ok(())
    }
}
