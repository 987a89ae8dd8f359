//! The console on a terminal: a thread
//! reads lines, the simulator task carries them out and answers over a channel. A
//! thread, not a tokio task, because a blocking read of stdin cannot be cancelled and
//! would hold up the runtime's shutdown.

use super::console::ConsoleCommand;
use super::serve::ConsoleRequest;
use std::io::{BufRead, Write};
use tokio::sync::{mpsc, oneshot};
use tokio_util::sync::CancellationToken;

/// Starts the console if stdin is a terminal; the receiver gets its commands (it stays
/// empty when there is no terminal). `quit`, or the end of input, cancels `shutdown`
/// once the answer is printed. With `after`, the console shows itself only once that
/// says so (or is dropped): the demo's banner comes first, not after a prompt.
pub(crate) fn start(
    enabled: bool,
    shutdown: CancellationToken,
    after: Option<std::sync::mpsc::Receiver<()>>,
) -> mpsc::Receiver<ConsoleRequest> {
    let (tx, rx) = mpsc::channel(4);
    if enabled && std::io::IsTerminal::is_terminal(&std::io::stdin()) {
        std::thread::spawn(move || {
            if let Some(after) = after {
                let _ = after.recv();
            }
            println!("mbgate sim console; `help` lists the commands");
            read_lines(tx);
            shutdown.cancel();
        });
    } else {
        // Keep the sender alive so the receiver simply never yields.
        std::mem::forget(tx);
    }
    rx
}

fn prompt() {
    print!("sim> ");
    let _ = std::io::stdout().flush();
}

fn read_lines(tx: mpsc::Sender<ConsoleRequest>) {
    prompt();
    let stdin = std::io::stdin();
    for line in stdin.lock().lines() {
        let Ok(line) = line else { break };
        match ConsoleCommand::parse(&line) {
            Ok(None) => {}
            Ok(Some(command)) => {
                let quit = command == ConsoleCommand::Quit;
                let (reply, answer) = oneshot::channel();
                if tx.blocking_send(ConsoleRequest { command, reply }).is_err() {
                    return;
                }
                match answer.blocking_recv() {
                    Ok(text) => println!("{text}"),
                    Err(_) => return,
                }
                if quit {
                    return;
                }
            }
            Err(e) => println!("{e}"),
        }
        prompt();
    }
    // End of input (Ctrl-D) quits, as `quit` does.
}
