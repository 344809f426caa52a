//! Reading scenario files: their shape and numbers ([`Scenario`]'s own checks), then whether
//! the motion they describe can be driven (checked by the motion planner). Kept apart from
//! both so that the scenario types never depend on the planner that reads them.

use std::path::Path;

use crate::SimError;
use crate::motion;
use crate::scenario::Scenario;

impl Scenario {
    /// Reads and checks a scenario file.
    ///
    /// # Errors
    /// [`SimError::Read`], [`SimError::Scenario`] with file, line, column and key path, or
    /// [`SimError::Invalid`] for values out of range.
    pub fn load(path: &Path) -> Result<Self, SimError> {
        let text = std::fs::read_to_string(path).map_err(|source| SimError::Read {
            path: path.to_owned(),
            source,
        })?;
        Self::parse(&text, path)
    }

    /// Parses scenario text; `file` names it in errors.
    ///
    /// # Errors
    /// As [`load`](Self::load).
    pub fn parse(text: &str, file: &Path) -> Result<Self, SimError> {
        let scenario: Self = serde_saphyr::from_str(text).map_err(|e| {
            let (at, message) = gprflow::graph::locate_yaml_error(file, text, &e);
            SimError::Scenario { at, message }
        })?;
        let wander_fits = |(i, run): (usize, &crate::scenario::Run)| match &run.wander {
            Some(wander) => motion::check_wander_fits(run, wander)
                .map_err(|m| gprflow_params::ParamError::new(&format!("runs.{i}.wander.sigma_m"), m)),
            None => Ok(()),
        };
        scenario
            .validate()
            .and_then(|()| scenario.runs.iter().enumerate().try_for_each(wander_fits))
            .map_err(|e| SimError::Invalid {
                at: gprflow::graph::locate_yaml_key(file, text, &e.key()),
                message: e.message,
            })?;
        Ok(scenario)
    }
}
