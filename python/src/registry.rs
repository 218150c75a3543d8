//! `scanloc.Registry`: a registry read from Python (runs, a run's record
//! and AUC table, artefacts by key, verification), as JSON and blob bytes
//! the Python package turns into DataFrames and arrays.

use std::path::Path;

use pyo3::prelude::*;
use pyo3::types::PyBytes;
use scanloc::registry::{Found, Registry};

use super::to_py;

fn open(path: &str) -> anyhow::Result<Registry> {
    if !Path::new(path).exists() {
        return Err(anyhow::Error::new(std::io::Error::new(
            std::io::ErrorKind::NotFound,
            format!("registry {path}: no such folder"),
        )));
    }
    Registry::open_existing(Path::new(path))
}

/// Every run, newest first (`scanloc registry runs --json`).
#[pyfunction]
fn _registry_runs(py: Python<'_>, path: &str) -> PyResult<String> {
    py.allow_threads(|| Ok(open(path)?.list_runs()?.to_json().to_string()))
        .map_err(to_py)
}

/// A run's record, with its steps and AUC table (JSON); `id` is a run id
/// or a unique prefix.
#[pyfunction]
fn _registry_run(py: Python<'_>, path: &str, id: &str) -> PyResult<String> {
    py.allow_threads(|| -> anyhow::Result<String> {
        let registry = open(path)?;
        match registry.resolve_id(id)? {
            Found::Run(run) => Ok(serde_json::to_string(&registry.run_record(&run)?)?),
            Found::Artefact(key) => Err(scanloc::error::input_error(format!(
                "{id}: the artefact {key}, not a run (Registry.artefact reads it)"
            ))),
        }
    })
    .map_err(to_py)
}

/// An artefact's blobs: (role, bytes).
type Blobs = Vec<(String, Vec<u8>)>;
type PyBlobs<'py> = Vec<(String, Bound<'py, PyBytes>)>;

/// An artefact's record (JSON) and its blobs as (role, bytes); `key` is a
/// content key or a unique prefix.
#[pyfunction]
fn _registry_artefact<'py>(
    py: Python<'py>,
    path: &str,
    key: &str,
) -> PyResult<(String, PyBlobs<'py>)> {
    let (record, blobs) = py
        .allow_threads(|| -> anyhow::Result<(String, Blobs)> {
            let registry = open(path)?;
            let key = match registry.resolve_id(key)? {
                Found::Artefact(key) => key,
                Found::Run(run) => {
                    return Err(scanloc::error::input_error(format!(
                        "{run}: a run, not an artefact (Registry.run reads it)"
                    )));
                }
            };
            let record = registry.artefact_record(&key)?.to_string();
            let stored = registry
                .artefact(&key)?
                .ok_or_else(|| scanloc::error::input_error(format!("{key}: no such artefact")))?;
            let mut blobs = Vec::new();
            for blob in &stored.blobs {
                let bytes = registry.blobs().get(&blob.sha256)?.map_err(|state| {
                    scanloc::error::CheckFailed(format!(
                        "{key}: blob {} ({}) is {state:?}: scanloc registry verify",
                        blob.sha256,
                        blob.role.as_str()
                    ))
                })?;
                blobs.push((blob.role.as_str().to_string(), bytes));
            }
            Ok((record, blobs))
        })
        .map_err(to_py)?;
    let blobs = blobs
        .into_iter()
        .map(|(role, bytes)| (role, PyBytes::new(py, &bytes)))
        .collect();
    Ok((record, blobs))
}

/// `scanloc registry verify --json`: the report.
#[pyfunction]
fn _registry_verify(py: Python<'_>, path: &str) -> PyResult<String> {
    py.allow_threads(|| Ok(serde_json::to_string(&open(path)?.verify()?)?))
        .map_err(to_py)
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(_registry_runs, m)?)?;
    m.add_function(wrap_pyfunction!(_registry_run, m)?)?;
    m.add_function(wrap_pyfunction!(_registry_artefact, m)?)?;
    m.add_function(wrap_pyfunction!(_registry_verify, m)?)?;
    Ok(())
}
