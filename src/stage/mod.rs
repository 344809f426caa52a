//! Stage SDK: what a stage declares, and the runtime that feeds it.

mod spec;

pub use spec::{InputPorts, InputSpec, ParamError, PortSpec, StageCatalog, StageInfo, parse_params};
