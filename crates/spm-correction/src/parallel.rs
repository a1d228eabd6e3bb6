//! The choice of threads for the image-sized loops (rows are independent).

use rayon::prelude::*;

use crate::CorrectionError;

/// How many threads the per-row loops of raster correction and resampling use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Parallelism {
    /// The calling thread only.
    #[default]
    Sequential,
    /// A dedicated pool of this many threads (1 behaves like [`Parallelism::Sequential`]).
    Threads(usize),
    /// Rayon's global pool (one thread per core unless `RAYON_NUM_THREADS` says otherwise).
    AllCores,
}

/// Runs `f(row_index, row)` over the rows of `buffer` (`row_len` entries each).
pub(crate) fn for_each_row<T, F>(
    parallelism: Parallelism,
    buffer: &mut [T],
    row_len: usize,
    f: F,
) -> Result<(), CorrectionError>
where
    T: Send,
    F: Fn(usize, &mut [T]) + Sync + Send,
{
    if row_len == 0 {
        return Ok(());
    }
    match parallelism {
        Parallelism::Sequential | Parallelism::Threads(0 | 1) => {
            buffer
                .chunks_mut(row_len)
                .enumerate()
                .for_each(|(i, r)| f(i, r));
            Ok(())
        }
        Parallelism::AllCores => {
            buffer
                .par_chunks_mut(row_len)
                .enumerate()
                .for_each(|(i, r)| f(i, r));
            Ok(())
        }
        Parallelism::Threads(n) => {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .map_err(|e| CorrectionError::ThreadPool(e.to_string()))?;
            pool.install(|| {
                buffer
                    .par_chunks_mut(row_len)
                    .enumerate()
                    .for_each(|(i, r)| f(i, r));
            });
            Ok(())
        }
    }
}
