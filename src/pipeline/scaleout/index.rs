//! Which task a worker is: `--index I --of N`, else what its engine tells it.
//!
//! | engine | index | count |
//! |---|---|---|
//! | flags | `--index` | `--of`, else the phase's tasks |
//! | SLURM array job | `SLURM_ARRAY_TASK_ID` − `SLURM_ARRAY_TASK_MIN` | `SLURM_ARRAY_TASK_COUNT` |
//! | Kubernetes Indexed Job | `JOB_COMPLETION_INDEX` | the phase's tasks (= `completions`) |
//! | AWS Batch array job | `AWS_BATCH_JOB_ARRAY_INDEX` | the phase's tasks (= array size) |
//! | none of them | 0 | 1: one task does the whole phase |
//!
//! A SLURM array must be contiguous with step 1 (`--array=0-3`, `--array=1-4`): with holes
//! (`--array=0,2,5`) an index does not say which share is whose, so it is refused. A task whose
//! index is at or past the phase's task count has nothing to do and succeeds.

use super::ScaleoutError;

/// A worker's place in its phase.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct TaskIndex {
    /// This task, `0..of`.
    pub index: u64,
    /// Tasks sharing the phase.
    pub of: u64,
    /// Where the index came from: `flags`, `slurm`, `kubernetes`, `aws-batch` or `default`.
    pub source: &'static str,
}

/// The task index from the flags, else from the environment `env` (a lookup such as
/// `|k| std::env::var(k).ok()`); `tasks` is the phase's task count from the plan.
///
/// # Errors
/// [`ScaleoutError::Index`] for a value that is not a number, `of` = 0, an index ≥ `of`, or a
/// SLURM array that is not contiguous.
pub fn resolve_index(
    index: Option<u64>,
    of: Option<u64>,
    tasks: u64,
    env: impl Fn(&str) -> Option<String>,
) -> Result<TaskIndex, ScaleoutError> {
    let num = |name: &str| -> Result<Option<u64>, ScaleoutError> {
        match env(name) {
            None => Ok(None),
            Some(v) if v.trim().is_empty() => Ok(None),
            Some(v) => v.trim().parse().map(Some).map_err(|_| {
                ScaleoutError::Index(format!("{name}={v} is not a non-negative integer"))
            }),
        }
    };
    let default_of = tasks.max(1);
    let (i, n, source) = if let Some(i) = index {
        (i, of.unwrap_or(default_of), "flags")
    } else if let Some(id) = num("SLURM_ARRAY_TASK_ID")? {
        let min = num("SLURM_ARRAY_TASK_MIN")?.unwrap_or(0);
        let count = num("SLURM_ARRAY_TASK_COUNT")?;
        let max = num("SLURM_ARRAY_TASK_MAX")?;
        let step = num("SLURM_ARRAY_TASK_STEP")?.unwrap_or(1);
        let Some(count) = count else {
            return Err(ScaleoutError::Index(
                "SLURM_ARRAY_TASK_ID is set without SLURM_ARRAY_TASK_COUNT; give --of".into(),
            ));
        };
        let contiguous = step == 1 && max.is_none_or(|m| m >= min && m - min + 1 == count);
        if !contiguous || id < min {
            return Err(ScaleoutError::Index(format!(
                "the SLURM array (ids {min}..={}, step {step}, {count} tasks) is not contiguous; \
                 submit --array=0-{} or give --index and --of",
                max.map_or_else(|| "?".to_string(), |m| m.to_string()),
                count.saturating_sub(1)
            )));
        }
        (id - min, of.unwrap_or(count), "slurm")
    } else if let Some(i) = num("JOB_COMPLETION_INDEX")? {
        (i, of.unwrap_or(default_of), "kubernetes")
    } else if let Some(i) = num("AWS_BATCH_JOB_ARRAY_INDEX")? {
        (i, of.unwrap_or(default_of), "aws-batch")
    } else {
        (0, of.unwrap_or(1), "default")
    };
    if n == 0 {
        return Err(ScaleoutError::Index("--of must be at least 1".into()));
    }
    if i >= n {
        return Err(ScaleoutError::Index(format!(
            "index {i} is not below the task count {n} (from {source})"
        )));
    }
    Ok(TaskIndex {
        index: i,
        of: n,
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env(vars: &[(&str, &str)]) -> impl Fn(&str) -> Option<String> {
        let v: Vec<(String, String)> = vars
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        move |k| v.iter().find(|(n, _)| n == k).map(|(_, x)| x.clone())
    }

    #[test]
    fn issue11_indices_come_from_flags_then_each_engine() {
        let r = |i, n, t, e: &[(&str, &str)]| resolve_index(i, n, t, env(e));
        let got = r(Some(2), Some(3), 9, &[("SLURM_ARRAY_TASK_ID", "1")]).unwrap();
        assert_eq!((got.index, got.of, got.source), (2, 3, "flags"));
        assert_eq!(r(Some(4), None, 9, &[]).unwrap().of, 9);
        let slurm = [
            ("SLURM_ARRAY_TASK_ID", "3"),
            ("SLURM_ARRAY_TASK_MIN", "1"),
            ("SLURM_ARRAY_TASK_MAX", "4"),
            ("SLURM_ARRAY_TASK_COUNT", "4"),
        ];
        let got = r(None, None, 9, &slurm).unwrap();
        assert_eq!((got.index, got.of, got.source), (2, 4, "slurm"));
        let holes = [
            ("SLURM_ARRAY_TASK_ID", "2"),
            ("SLURM_ARRAY_TASK_MIN", "0"),
            ("SLURM_ARRAY_TASK_MAX", "5"),
            ("SLURM_ARRAY_TASK_COUNT", "3"),
        ];
        assert!(
            r(None, None, 9, &holes)
                .unwrap_err()
                .to_string()
                .contains("contiguous")
        );
        let k8s = r(None, None, 7, &[("JOB_COMPLETION_INDEX", "6")]).unwrap();
        assert_eq!((k8s.index, k8s.of, k8s.source), (6, 7, "kubernetes"));
        assert!(r(None, None, 7, &[("JOB_COMPLETION_INDEX", "7")]).is_err());
        let aws = r(None, None, 5, &[("AWS_BATCH_JOB_ARRAY_INDEX", "0")]).unwrap();
        assert_eq!((aws.index, aws.of, aws.source), (0, 5, "aws-batch"));
        let none = r(None, None, 5, &[]).unwrap();
        assert_eq!((none.index, none.of, none.source), (0, 1, "default"));
        assert!(r(None, None, 5, &[("JOB_COMPLETION_INDEX", "x")]).is_err());
        assert!(r(Some(0), Some(0), 5, &[]).is_err());
        // A phase with no task (globals of a method without them) still has one index 0.
        assert_eq!(
            r(None, None, 0, &[("JOB_COMPLETION_INDEX", "0")])
                .unwrap()
                .of,
            1
        );
    }
}
