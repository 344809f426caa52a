//! `gprflow convert INPUT --to mcap`: a radar file (CMU-GPR folder, DZT, DT1/HD, or another
//! MCAP) to one of our recordings, through the loader the `ingest` stage plays
//! (`gprflow_ingest::load`).

use std::collections::BTreeMap;
use std::io::Write as _;
use std::path::Path;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use gprflow::record::{Recorder, RunMetadata};
use gprflow_ingest::SourceFormat;
use gprflow_ingest::load::{LoadOptions, Port, load};

/// What `gprflow convert` writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OutputFormat {
    /// An MCAP recording (from a radar file or another recording).
    Mcap,
    /// A TUM trajectory file (from a recording's pose topic).
    Tum,
}

/// The output format: `to` when given (`mcap` or `tum`), else from `output`'s extension
/// (`.mcap`; `.tum` or `.txt`).
///
/// # Errors
/// Neither says which.
pub fn output_format(to: Option<&str>, output: &Path) -> Result<OutputFormat> {
    let ext = output.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    match (to, ext.as_deref()) {
        (Some("mcap"), _) | (None, Some("mcap")) => Ok(OutputFormat::Mcap),
        (Some("tum"), _) | (None, Some("tum" | "txt")) => Ok(OutputFormat::Tum),
        (Some(other), _) => bail!("--to {other}: not an output format (mcap or tum)"),
        (None, _) => bail!(
            "{}: cannot tell the output format from the extension (.mcap, .tum or .txt); give --to mcap or --to tum",
            output.display()
        ),
    }
}

/// Writes `input` as an MCAP recording at `output`: traces on `/gpr/trace`, sweeps on
/// `/lgpr/sweep`, IMU on `/imu/data`, wheel on `/wheel/odometry`, truth on `/truth/pose`.
///
/// # Errors
/// The reader's error (naming file, record and field) or a write error.
pub fn convert_to_mcap(input: &Path, format: SourceFormat, output: &Path) -> Result<ExitCode> {
    let loaded =
        load(input, format, &LoadOptions::default()).with_context(|| format!("{}: cannot convert", input.display()))?;
    let mut meta = RunMetadata::this_build();
    meta.graph_name = format!("convert {}", input.display());
    let first = loaded.messages.first().map_or(0, |m| m.1);
    let mut rec = Recorder::create_reproducible(output, &meta, u64::try_from(first).unwrap_or(0))?;
    let mut fields = BTreeMap::new();
    fields.insert("source".to_owned(), input.display().to_string());
    fields.insert("summary".to_owned(), loaded.summary.clone());
    fields.insert("skipped_records".to_owned(), loaded.dropped.len().to_string());
    rec.write_metadata("convert", fields)?;
    let mut channels = BTreeMap::new();
    let mut seqs: BTreeMap<Port, u64> = BTreeMap::new();
    for (port, stamp, data) in &loaded.messages {
        let ch = match channels.get(port) {
            Some(ch) => *ch,
            None => {
                let ch = rec.add_topic(port.topic(), port.msg_type())?;
                channels.insert(*port, ch);
                ch
            }
        };
        let seq = seqs.entry(*port).or_default();
        rec.write(ch, *seq, *stamp, data)?;
        *seq += 1;
    }
    rec.finish()?;
    let mut out = std::io::stdout().lock();
    writeln!(out, "{}: {}", input.display(), loaded.summary)?;
    for (port, n) in &seqs {
        writeln!(out, "  {:<28} {n} messages", port.topic())?;
    }
    for d in &loaded.dropped {
        writeln!(out, "  reported: {d}")?;
    }
    writeln!(out, "written to {}", output.display())?;
    Ok(ExitCode::SUCCESS)
}
