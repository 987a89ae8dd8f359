//! `mbgate read` and `mbgate write` (docs/read-write.md): exit 0 on a normal
//! response, 3 on an exception response, 1 on no answer (timeout, connection refused,
//! port missing, a reply that answers something else), 2 on bad arguments. With
//! `--poll`, Ctrl-C ends the session with its summary; the code is the last request's.

use super::client_args::{BadValue, CommonArgs};
use super::exit;
use super::signals::{self, Stops};
use crate::frame::request::{Request, RequestError};
use crate::tools::client::{session, ClientTransport, Outcome};
use std::process::ExitCode;

pub(crate) use super::client_args::{ReadArgs, WriteArgs};

/// Why a request cannot be sent: the message names the value or flag.
#[derive(Debug, thiserror::Error)]
enum Unsendable {
    /// A value or flag combination of the command line.
    #[error(transparent)]
    Args(#[from] BadValue),
    /// A request the protocol does not allow (a quantity out of range...).
    #[error(transparent)]
    Request(#[from] RequestError),
}

/// The request's PDU and the transport to send it on, or why they cannot be had.
fn prepare(
    common: &CommonArgs,
    request: &Request,
) -> Result<(ClientTransport, Vec<u8>), Unsendable> {
    let pdu = request.pdu()?;
    Ok((common.transport()?, pdu))
}

/// `mbgate read`.
pub(crate) fn read(args: ReadArgs) -> ExitCode {
    let request = args.request();
    run(&args.common, &request)
}

/// `mbgate write`.
pub(crate) fn write(args: WriteArgs) -> ExitCode {
    match args.request() {
        Ok(request) => run(&args.common, &request),
        Err(e) => exit::usage(e),
    }
}

fn run(common: &CommonArgs, request: &Request) -> ExitCode {
    let (transport, pdu) = match prepare(common, request) {
        Ok(ready) => ready,
        Err(e) => return exit::usage(e),
    };
    let rt = match signals::runtime(exit::FAILED) {
        Ok(rt) => rt,
        Err(code) => return code,
    };
    let outcome = rt.block_on(async {
        // Without --poll, Ctrl-C keeps its default action: one request ends at once.
        let stop = match common.poll {
            Some(_) => signals::stop_on(Stops::Interrupt),
            None => tokio_util::sync::CancellationToken::new(),
        };
        session(&common.session(), transport, &pdu, stop).await
    });
    exit::code(match outcome {
        Outcome::Reply => exit::OK,
        Outcome::NoAnswer => exit::FAILED,
        Outcome::Exception => exit::OTHER,
    })
}
