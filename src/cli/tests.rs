//! Tests of cli.

use super::*;

/// clap's own checks of every subcommand's flags (conflicts, requires and groups
/// that name flags there are, no two flags of one name).
#[test]
fn the_command_line_is_consistent() {
    command().debug_assert();
}

/// Each subcommand parses to its own variant, its flags to their fields' types.
#[test]
fn each_subcommand_parses() {
    let parse = |line: &[&str]| Cli::try_parse_from(line).map(|c| c.command);
    assert!(matches!(
        parse(&["mbgate", "read", "holding", "0x6B", "3"]),
        Ok(CliCommand::Read(_))
    ));
    assert!(matches!(
        parse(&["mbgate", "status", "--metrics", "127.0.0.1:9"]),
        Ok(CliCommand::Status(_))
    ));
    assert!(matches!(
        parse(&[
            "mbgate",
            "sim",
            "--serial",
            "/dev/ttyS9",
            "--role",
            "master"
        ]),
        Ok(CliCommand::Sim(_))
    ));
    assert!(matches!(
        parse(&["mbgate", "wire", "a", "b", "--a", "9600,8E1"]),
        Ok(CliCommand::Wire(_))
    ));
    let refused = parse(&["mbgate", "wire", "a", "b", "--format", "9N1"]).unwrap_err();
    assert_eq!(refused.exit_code(), i32::from(exit::USAGE));
    assert!(
        refused.to_string().contains("expected a format like 8N1"),
        "{refused}"
    );
}
