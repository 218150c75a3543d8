//! Benchmarks behind `scanloc bench`: each measures scanloc and, where one
//! is available on the machine, a reference implementation in the same run,
//! so speed is reported as a ratio measured under the same load.

pub(crate) mod cnn;
pub mod link;
pub(crate) mod locate;
pub(crate) mod reference;
pub(crate) mod simulate;
pub mod tradeoff;
