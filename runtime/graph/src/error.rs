//! What can be wrong with a graph file, and where.

use std::fmt;
use std::path::PathBuf;
use std::str::FromStr;

/// A 1-based line and column in a graph file (columns count characters).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Position {
    /// Line, from 1.
    pub line: usize,
    /// Column, from 1.
    pub column: usize,
}

impl fmt::Display for Position {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}", self.line, self.column)
    }
}

/// Where a problem is: the file, the position in it when there is one, and the key path
/// (`nodes.gain.inputs.trace`; empty for the whole file).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Location {
    /// The graph file as named by the caller.
    pub file: PathBuf,
    /// Line and column of the offending key or value.
    pub position: Option<Position>,
    /// Keys from the top of the file down to the offending one, joined by `.`.
    pub key_path: String,
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.file.display())?;
        if let Some(position) = self.position {
            write!(f, ":{position}")?;
        }
        if !self.key_path.is_empty() {
            write!(f, ": {}", self.key_path)?;
        }
        Ok(())
    }
}

/// A graph file that cannot be run, with the place and the reason.
///
/// Display reads `file:line:column: key.path: what is wrong`. Locations are boxed to keep
/// the error small.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GraphError {
    /// The file cannot be read.
    #[error("{}: cannot read graph file: {source}", file.display())]
    Io {
        /// The file.
        file: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The file is not valid YAML.
    #[error("{at}: YAML syntax error: {message}")]
    Syntax {
        /// Where.
        at: Box<Location>,
        /// The parser's words.
        message: String,
    },
    /// Valid YAML, but not the graph file format: unknown, missing or wrongly typed field.
    #[error("{at}: {message}")]
    Structure {
        /// Where.
        at: Box<Location>,
        /// What is wrong.
        message: String,
    },
    /// The same key twice in one mapping (two nodes of the same name, ...).
    #[error("{at}: duplicate key `{key}` (first at line {}, column {})", first.line, first.column)]
    DuplicateKey {
        /// Where the second one is.
        at: Box<Location>,
        /// The key.
        key: String,
        /// Where the first one is.
        first: Position,
    },
    /// A node listed on two hosts.
    #[error("{at}: node `{node}` is already on host `{first_host}`; a node runs on one host")]
    NodeOnTwoHosts {
        /// Where the second listing is.
        at: Box<Location>,
        /// The node.
        node: String,
        /// The host that lists it first.
        first_host: String,
    },
    /// `stage:` names no stage kind of the catalog.
    #[error("{at}: unknown stage `{stage}` (stages are: {known})")]
    UnknownStage {
        /// Where.
        at: Box<Location>,
        /// The name as written.
        stage: String,
        /// The stage kinds there are, comma separated.
        known: String,
    },
    /// The stage rejects its `params`.
    #[error("{at}: bad parameter for stage `{stage}`: {message}")]
    BadParam {
        /// Where (`nodes.N.params.<key>`).
        at: Box<Location>,
        /// The stage kind.
        stage: String,
        /// The stage's words.
        message: String,
    },
    /// An input wired to a node that does not exist.
    #[error("{at}: no node `{node}` (nodes are: {known})")]
    NoSuchNode {
        /// Where.
        at: Box<Location>,
        /// The node named by the reference.
        node: String,
        /// The nodes there are.
        known: String,
    },
    /// An input wired to an output its node does not have.
    #[error("{at}: node `{node}` has no output `{output}` (its outputs are: {known})")]
    NoSuchOutput {
        /// Where.
        at: Box<Location>,
        /// The node named by the reference.
        node: String,
        /// The output named by the reference.
        output: String,
        /// The outputs that node has.
        known: String,
    },
    /// A required input of a stage left unwired.
    #[error("{at}: stage `{stage}` needs input `{input}` ({msg_type}), which is not wired")]
    MissingInput {
        /// Where (the node's `inputs`, or the node).
        at: Box<Location>,
        /// The stage kind.
        stage: String,
        /// The input.
        input: String,
        /// Its message type.
        msg_type: String,
    },
    /// An input the stage does not declare.
    #[error("{at}: stage `{stage}` has no input `{input}` (its inputs are: {known})")]
    UnknownInput {
        /// Where.
        at: Box<Location>,
        /// The stage kind.
        stage: String,
        /// The input as written.
        input: String,
        /// The inputs it declares.
        known: String,
    },
    /// An input wired to an output of another message type.
    #[error("{at}: input `{input}` takes {expected} but `{from}` is {actual}")]
    TypeMismatch {
        /// Where.
        at: Box<Location>,
        /// The input.
        input: String,
        /// The type the input takes.
        expected: String,
        /// The output it is wired to (`node/output`).
        from: String,
        /// That output's type.
        actual: String,
    },
    /// `hosts:` is present but a node is on none of them.
    #[error("{at}: node `{node}` is on no host (hosts are: {hosts}); with `hosts:` every node needs one")]
    NodeOnNoHost {
        /// Where the node is declared.
        at: Box<Location>,
        /// The node.
        node: String,
        /// The hosts there are.
        hosts: String,
    },
    /// A host lists a node that does not exist.
    #[error("{at}: host `{host}` lists `{node}`, which is not a node (nodes are: {known})")]
    UnknownHostNode {
        /// Where.
        at: Box<Location>,
        /// The host.
        host: String,
        /// The name as listed.
        node: String,
        /// The nodes there are.
        known: String,
    },
    /// A host's zenoh settings cannot work (bad endpoint, mode, certificates, access list).
    #[error("{at}: host `{host}`: {message}")]
    BadHost {
        /// Where (`hosts.NAME.zenoh`).
        at: Box<Location>,
        /// The host.
        host: String,
        /// What is wrong.
        message: String,
    },
    /// An input reference that is not `node/output`.
    #[error("{at}: `{reference}` is not an output reference of the form `node/output`")]
    BadReference {
        /// Where.
        at: Box<Location>,
        /// The reference as written.
        reference: String,
    },
    /// `${name}` names no variable declared under `inputs:`.
    #[error("{at}: unknown variable `{name}` (variables are: {known}); declare it under `inputs:`")]
    UnknownVariable {
        /// Where the reference is.
        at: Box<Location>,
        /// The variable name.
        name: String,
        /// The variables there are.
        known: String,
    },
    /// A `${` without its closing `}`.
    #[error("{at}: `${{` without a closing `}}` in `{text}`")]
    UnclosedVariable {
        /// Where.
        at: Box<Location>,
        /// The string as written.
        text: String,
    },
    /// A command-line override (`--set name=value`) for a variable the file does not declare.
    #[error("{at}: `--set {name}=...` names no variable of this graph (variables are: {known})")]
    UnknownOverride {
        /// The file's `inputs:`.
        at: Box<Location>,
        /// The variable name given.
        name: String,
        /// The variables there are.
        known: String,
    },
    /// A cycle of inputs none of which is a feedback input: it would deadlock.
    #[error(
        "{at}: cycle without a feedback input: {cycle}; it would deadlock (give one of these inputs \
         the long form `{{ from: ..., feedback_delay_s: ... }}`)"
    )]
    Cycle {
        /// The input that closes the cycle.
        at: Box<Location>,
        /// The nodes around the cycle, `a -> b -> a`.
        cycle: String,
    },
    /// `feedback_delay_s` not a positive, finite number of seconds.
    #[error("{at}: feedback_delay_s must be a positive number of seconds (at least 1 ns), got {value}")]
    BadFeedbackDelay {
        /// Where.
        at: Box<Location>,
        /// The value as read.
        value: f64,
    },
}

/// The category of a [`GraphError`], for tests and tools that branch on it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum GraphErrorKind {
    /// The file cannot be read.
    Io,
    /// YAML syntax.
    Syntax,
    /// Unknown, missing or wrongly typed field of the file format.
    Structure,
    /// `stage:` names no known stage kind.
    UnknownStage,
    /// The stage rejects its parameters.
    BadParam,
    /// An input wired to a missing node or output.
    DanglingInput,
    /// A required input not wired.
    MissingInput,
    /// An input the stage does not declare.
    UnknownInput,
    /// Input and output message types differ.
    TypeMismatch,
    /// A duplicate key or a node on two hosts.
    DuplicateName,
    /// `hosts:` present but a node is on none.
    NodeOnNoHost,
    /// A host lists a node that does not exist.
    UnknownHostNode,
    /// A host's zenoh settings (endpoints, mode, TLS, access list) or `record.host`.
    BadHost,
    /// A malformed `node/output` reference.
    BadReference,
    /// An undeclared or malformed variable, in the file or on the command line.
    UnknownVariable,
    /// A cycle with no feedback input.
    Cycle,
    /// `feedback_delay_s` not positive or not finite.
    BadFeedbackDelay,
}

impl GraphErrorKind {
    /// Every kind, in declaration order.
    pub const ALL: [GraphErrorKind; 17] = [
        Self::Io,
        Self::Syntax,
        Self::Structure,
        Self::UnknownStage,
        Self::BadParam,
        Self::DanglingInput,
        Self::MissingInput,
        Self::UnknownInput,
        Self::TypeMismatch,
        Self::DuplicateName,
        Self::NodeOnNoHost,
        Self::UnknownHostNode,
        Self::BadHost,
        Self::BadReference,
        Self::UnknownVariable,
        Self::Cycle,
        Self::BadFeedbackDelay,
    ];

    /// The kind's name as written in code (`DanglingInput`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Io => "Io",
            Self::Syntax => "Syntax",
            Self::Structure => "Structure",
            Self::UnknownStage => "UnknownStage",
            Self::BadParam => "BadParam",
            Self::DanglingInput => "DanglingInput",
            Self::MissingInput => "MissingInput",
            Self::UnknownInput => "UnknownInput",
            Self::TypeMismatch => "TypeMismatch",
            Self::DuplicateName => "DuplicateName",
            Self::NodeOnNoHost => "NodeOnNoHost",
            Self::UnknownHostNode => "UnknownHostNode",
            Self::BadHost => "BadHost",
            Self::BadReference => "BadReference",
            Self::UnknownVariable => "UnknownVariable",
            Self::Cycle => "Cycle",
            Self::BadFeedbackDelay => "BadFeedbackDelay",
        }
    }
}

impl fmt::Display for GraphErrorKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A name that is not a [`GraphErrorKind`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("no graph error kind `{0}`")]
pub struct UnknownErrorKind(pub String);

impl FromStr for GraphErrorKind {
    type Err = UnknownErrorKind;

    /// Parses a kind's name (`DanglingInput`), as written in `# expect:` lines of fixtures.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|kind| kind.name() == s)
            .ok_or_else(|| UnknownErrorKind(s.to_owned()))
    }
}

impl GraphError {
    /// The category of this error.
    pub fn kind(&self) -> GraphErrorKind {
        use GraphErrorKind as K;
        match self {
            Self::Io { .. } => K::Io,
            Self::Syntax { .. } => K::Syntax,
            Self::Structure { .. } => K::Structure,
            Self::DuplicateKey { .. } | Self::NodeOnTwoHosts { .. } => K::DuplicateName,
            Self::UnknownStage { .. } => K::UnknownStage,
            Self::BadParam { .. } => K::BadParam,
            Self::NoSuchNode { .. } | Self::NoSuchOutput { .. } => K::DanglingInput,
            Self::MissingInput { .. } => K::MissingInput,
            Self::UnknownInput { .. } => K::UnknownInput,
            Self::TypeMismatch { .. } => K::TypeMismatch,
            Self::NodeOnNoHost { .. } => K::NodeOnNoHost,
            Self::UnknownHostNode { .. } => K::UnknownHostNode,
            Self::BadHost { .. } => K::BadHost,
            Self::BadReference { .. } => K::BadReference,
            Self::UnknownVariable { .. } | Self::UnclosedVariable { .. } | Self::UnknownOverride { .. } => {
                K::UnknownVariable
            }
            Self::Cycle { .. } => K::Cycle,
            Self::BadFeedbackDelay { .. } => K::BadFeedbackDelay,
        }
    }

    /// Where the problem is; `None` only for [`GraphError::Io`].
    pub fn location(&self) -> Option<&Location> {
        match self {
            Self::Io { .. } => None,
            Self::Syntax { at, .. }
            | Self::Structure { at, .. }
            | Self::DuplicateKey { at, .. }
            | Self::NodeOnTwoHosts { at, .. }
            | Self::UnknownStage { at, .. }
            | Self::BadParam { at, .. }
            | Self::NoSuchNode { at, .. }
            | Self::NoSuchOutput { at, .. }
            | Self::MissingInput { at, .. }
            | Self::UnknownInput { at, .. }
            | Self::TypeMismatch { at, .. }
            | Self::NodeOnNoHost { at, .. }
            | Self::UnknownHostNode { at, .. }
            | Self::BadHost { at, .. }
            | Self::BadReference { at, .. }
            | Self::UnknownVariable { at, .. }
            | Self::UnclosedVariable { at, .. }
            | Self::UnknownOverride { at, .. }
            | Self::Cycle { at, .. }
            | Self::BadFeedbackDelay { at, .. } => Some(at.as_ref()),
        }
    }
}

/// Joins names for an error message: `a, b, c`, or `none`.
pub(crate) fn list<'a>(names: impl IntoIterator<Item = &'a str>) -> String {
    let joined = names.into_iter().collect::<Vec<_>>().join(", ");
    if joined.is_empty() { "none".to_owned() } else { joined }
}
