//! `dsq`: the command-line fitter of bevy_deformable_sq.
//!
//! ```text
//! dsq fit (POINTS | --image IMAGE | --scene FILE | --paper egg|mug|pestle|doll) [OPTIONS]
//! dsq track FRAMES... (--init PARAMS.json | --roi x0,y0,x1,y1) [--intrinsics CAM.json] [OPTIONS]
//! ```
//!
//! `dsq fit --help` and `dsq track --help` list every option. Progress goes to stderr; stdout gets one JSON line per
//! fitted part and a summary line last. Bad input exits with code 2 and a one-line message.
//! It needs no Bevy: `cargo install --path . --no-default-features` gives a working fitter
//! (only `--app`, which runs the fit through the plugin, needs the `bevy` feature).

mod args;
mod batch;
mod fit;
mod track;

use clap::error::ErrorKind;
use clap::{Parser, Subcommand};
use std::process::ExitCode;

/// Deformable superquadrics (Terzopoulos & Metaxas, PAMI 1991): fit them to point clouds,
/// images and scene files.
#[derive(Parser, Debug)]
#[command(name = "dsq", version)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// The subcommands.
#[derive(Subcommand, Debug)]
enum Command {
    /// Fit a model to a point cloud (OBJ or PLY), the parts of an image, every part of a scene
    /// file, or one of the paper's experiments, and print the fit as JSON lines.
    Fit(Box<args::FitArgs>),
    /// Follow one superquadric through a depth video (16-bit PNG depth frames or camera-frame
    /// clouds), starting from a fit or a pixel box, and print one JSON line per frame.
    Track(Box<track::TrackArgs>),
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) if !e.use_stderr() => {
            // --help and --version.
            let _ = e.print();
            return ExitCode::SUCCESS;
        }
        Err(e) if e.kind() == ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand => {
            // `dsq` alone: the usage, as an error.
            let _ = e.print();
            return ExitCode::from(2);
        }
        Err(e) => return fail(&e.render().to_string()),
    };
    let result = match cli.command {
        Command::Fit(a) => a.resolve().and_then(|(a, points)| fit::run(a, points)),
        Command::Track(a) => track::run(*a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => fail(&e),
    }
}

/// Prints one line to stdout. When the reader has gone (`dsq fit *.ply | head`), the program
/// ends quietly, as any filter does on a closed pipe; another write error ends it with code 2.
pub fn emit(line: impl std::fmt::Display) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    if let Err(e) = writeln!(out, "{line}").and_then(|()| out.flush()) {
        if e.kind() == std::io::ErrorKind::BrokenPipe {
            std::process::exit(0);
        }
        eprintln!("error: cannot write to stdout: {e}");
        std::process::exit(2);
    }
}

/// Prints `message`'s first line to stderr as one line, `error: …`, and gives exit code 2.
fn fail(message: &str) -> ExitCode {
    let line = message.lines().find(|l| !l.trim().is_empty()).unwrap_or("");
    let line = line.strip_prefix("error: ").unwrap_or(line);
    eprintln!("error: {line}");
    ExitCode::from(2)
}
