//! `mbgate hash-password`: a bcrypt hash of a password for the metrics listener's web
//! configuration file (`basic_auth_users`, docs/watching.md), as `htpasswd -nBC 10`
//! makes one. The password is read from the terminal with its echo off, twice, or
//! from the first line of standard input; never from the command line, which `ps`
//! shows anyone.

use super::exit;
use std::io::{BufRead, IsTerminal, Write};
use std::process::ExitCode;

/// `mbgate hash-password`'s flags.
#[derive(Debug, clap::Args)]
pub(crate) struct HashArgs {
    /// bcrypt's cost: each step doubles the time of a check (10: about 50 ms on a PC, some hundreds on a Raspberry Pi); 4 to 16
    #[arg(long, value_name = "N", default_value_t = 10, value_parser = clap::value_parser!(u32).range(4..=16))]
    cost: u32,
    /// Print `NAME: HASH`, a line of basic_auth_users
    #[arg(long, value_name = "NAME")]
    user: Option<String>,
}

/// The terminal on standard input with its echo off until dropped.
struct NoEcho(Option<libc::termios>);

impl NoEcho {
    fn new() -> NoEcho {
        let mut t = std::mem::MaybeUninit::<libc::termios>::uninit();
        #[allow(unsafe_code)]
        // SAFETY: tcgetattr(3) writes a whole termios into `t`, valid for writes of its
        // size, and is only read after it said so (0); descriptor 0 stays open.
        let saved = unsafe { (libc::tcgetattr(0, t.as_mut_ptr()) == 0).then(|| t.assume_init()) };
        if let Some(saved) = saved {
            let mut quiet = saved;
            quiet.c_lflag &= !libc::ECHO;
            quiet.c_lflag |= libc::ECHONL;
            #[allow(unsafe_code)]
            // SAFETY: `quiet` is a termios tcgetattr filled, one flag changed.
            unsafe {
                libc::tcsetattr(0, libc::TCSANOW, &quiet);
            }
        }
        NoEcho(saved)
    }
}

impl Drop for NoEcho {
    fn drop(&mut self) {
        if let Some(saved) = &self.0 {
            #[allow(unsafe_code)]
            // SAFETY: `saved` is the termios tcgetattr gave for descriptor 0.
            unsafe {
                libc::tcsetattr(0, libc::TCSANOW, saved);
            }
        }
    }
}

/// One line of standard input, without its line end.
fn line(stdin: &mut impl BufRead) -> Option<String> {
    let mut s = String::new();
    match stdin.read_line(&mut s) {
        Ok(0) | Err(_) => None,
        Ok(_) => Some(s.trim_end_matches(['\n', '\r']).to_owned()),
    }
}

/// `mbgate hash-password`.
pub(crate) fn main(args: HashArgs) -> ExitCode {
    if let Some(u) = &args.user {
        if u.is_empty() || u.contains(':') || u.chars().any(char::is_control) {
            return exit::usage(
                "--user: a user name is not empty and has no ':' or control character",
            );
        }
    }
    let mut stdin = std::io::stdin().lock();
    let password = if std::io::stdin().is_terminal() {
        let _quiet = NoEcho::new();
        eprint!("password: ");
        let _ = std::io::stderr().flush();
        let first = line(&mut stdin);
        eprint!("again: ");
        let _ = std::io::stderr().flush();
        let again = line(&mut stdin);
        if first != again {
            return exit::failed("the two passwords differ; nothing printed");
        }
        first
    } else {
        line(&mut stdin)
    };
    let Some(password) = password.filter(|p| !p.is_empty()) else {
        return exit::failed("no password read (it is read from the terminal or standard input)");
    };
    match bcrypt::hash(&password, args.cost) {
        Ok(h) => {
            // htpasswd's prefix, which every reader of the format takes.
            let h = format!("$2y${}", &h[4..]);
            match &args.user {
                Some(u) => println!("{u}: {h}"),
                None => println!("{h}"),
            }
            exit::code(exit::OK)
        }
        Err(e) => exit::failed(format!("cannot hash it: {e}")),
    }
}
