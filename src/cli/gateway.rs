//! `mbgate run` and `mbgate check-config`: the configuration file with the flags on
//! top, checked (TLS files too), then run until a signal, or described.

use super::exit;
use super::signals::{self, Stops};
use crate::cli::overrides::Overrides;
use crate::config::{self, Config};
use std::path::PathBuf;
use std::process::ExitCode;

/// Why a configuration cannot be run: the file or a flag, or a TLS file it names.
#[derive(Debug, thiserror::Error)]
pub(crate) enum Unusable {
    /// The file, or a flag over it.
    #[error("{0}")]
    Config(#[from] config::ConfigError),
    /// A certificate or key that cannot be used (docs/security.md).
    #[error("{0}")]
    Tls(#[from] crate::tls::TlsError),
    /// The metrics listener's web configuration file (docs/watching.md).
    #[error("{0}")]
    Web(#[from] crate::ops::metrics::web::WebConfigError),
}

/// `mbgate check-config`: exit 0 valid, 2 not.
pub(crate) fn check_config(
    file: PathBuf,
    print: bool,
    lines: bool,
    overrides: &Overrides,
) -> ExitCode {
    match checked(Some(file.clone()), overrides) {
        Ok(cfg) => {
            if lines {
                print!("{}", config::to_toml_lines(&cfg));
            } else if print {
                print!("{}", config::to_toml(&cfg));
            } else {
                println!("OK: {}", file.display());
                print!("{}", config::describe::summary(&cfg));
                if let (Some(_), Ok(web)) = (
                    cfg.metrics.listen,
                    crate::ops::metrics::web::WebAccess::load(&cfg.metrics.web_config),
                ) {
                    if web.file.is_some() {
                        println!("  # who: {}", web.said());
                    }
                }
            }
            for warning in crate::gateway::warnings(&cfg) {
                eprintln!("mbgate: warning: {warning}");
            }
            exit::code(exit::OK)
        }
        Err(e) => exit::usage(e),
    }
}

/// `mbgate run`: exit 2 on a bad configuration, 1 on a failure while running, 0 once
/// stopped by SIGTERM or SIGINT.
pub(crate) fn run(file: Option<PathBuf>, overrides: Overrides) -> ExitCode {
    // Under journald these lines get the error priority too.
    let prefix = crate::ops::logging::error_prefix();
    let cfg = match checked(file.clone(), &overrides) {
        Ok(cfg) => cfg,
        Err(e) => {
            eprintln!("{prefix}mbgate: {e}");
            return exit::code(exit::USAGE);
        }
    };
    // A reload reads the file again and puts the same flags on top.
    let load = Box::new(move || effective(file.clone(), &overrides));
    crate::ops::logging::init(&cfg.log);
    let rt = match signals::runtime(exit::FAILED) {
        Ok(rt) => rt,
        Err(code) => return code,
    };
    let ran = rt.block_on(async {
        let shutdown = signals::stop_on(Stops::TermInt);
        // Every line, whichever side its device is on (a gateway of master lines
        // alone listens for no Modbus/TCP master).
        crate::gateway::run_reloading(cfg, load, shutdown).await
    });
    match ran {
        Ok(_) => exit::code(exit::OK),
        Err(e) => {
            eprintln!("{prefix}mbgate: {}", exit::said(&e));
            exit::code(exit::FAILED)
        }
    }
}

/// The file (or the defaults), then the flags on top.
fn effective(file: Option<PathBuf>, overrides: &Overrides) -> Result<Config, config::ConfigError> {
    let mut cfg = match file {
        Some(path) => config::load(&path)?,
        None => Config::default(),
    };
    overrides.apply(&mut cfg)?;
    Ok(cfg)
}

/// [`effective`], and every TLS file it names loaded, the metrics listener's web
/// configuration too: a certificate, key or password hash that cannot be used is a bad
/// configuration too (docs/security.md, docs/watching.md).
fn checked(file: Option<PathBuf>, overrides: &Overrides) -> Result<Config, Unusable> {
    let cfg = effective(file, overrides)?;
    crate::tls::check(&cfg)?;
    crate::ops::metrics::web::check(&cfg)?;
    Ok(cfg)
}
