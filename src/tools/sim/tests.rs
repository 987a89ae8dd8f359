//! Tests of tools::sim.

use super::*;

fn run(d: &mut Device, line: &str) -> ConsoleOutcome {
    d.execute(ConsoleCommand::parse(line).unwrap().unwrap())
}

#[test]
fn console_manages_generic_devices() {
    let mut d = Device::generic(&[1], 10, 10, 3);
    assert_eq!(
        run(&mut d, "add 2 20 30").text,
        "added unit 2: 20 coils, 30 registers"
    );
    assert_eq!(run(&mut d, "add 2").text, "unit 2 exists; remove it first");
    assert_eq!(
        run(&mut d, "add 3 5").text,
        "coils and registers must be 10..65536"
    );
    let list = run(&mut d, "list").text;
    assert!(list.contains("unit 1: 10 coils, 10 registers"), "{list}");
    assert!(list.contains("unit 2: 20 coils, 30 registers"), "{list}");
    assert_eq!(
        run(&mut d, "set 2 holding 29 7").text,
        "unit 2 holding 29 = 7"
    );
    assert_eq!(
        run(&mut d, "set 2 holding 30 7").text,
        "unit 2 has no holding 30"
    );
    assert_eq!(d.answer(2, &[3, 0, 29, 0, 1]).reply, Some(vec![3, 2, 0, 7]));
    assert_eq!(run(&mut d, "remove 2").text, "removed unit 2");
    assert_eq!(d.answer(2, &[3, 0, 29, 0, 1]), Answer::silent());
    assert!(run(&mut d, "quit").quit);
}

#[test]
fn console_sets_cie_m10_inputs_and_notifies() {
    let mut d = Device::new(
        Profile::CieM10(cie_m10::CieM10 {
            notify: true,
            ..Default::default()
        }),
        0,
    );
    let o = run(&mut d, "input 0 on");
    assert_eq!(o.text, "inputs 00000001");
    assert_eq!(o.notification, Some(vec![3, 2, 0, 1]));
    assert_eq!(
        run(&mut d, "input 0 on").notification,
        None,
        "no change, no notification"
    );
    assert_eq!(
        run(&mut d, "inputs 0xF0").notification,
        Some(vec![3, 2, 0, 0xF0])
    );
    assert_eq!(d.toggle(), Some(vec![3, 2, 0, 0xF1]));
    assert_eq!(
        run(&mut d, "add 2").text,
        "the cie-m10 profile is one device; use --profile generic"
    );
}

#[test]
fn same_seed_same_discrete_inputs() {
    let a = Device::generic(&[1, 2], 64, 10, 42);
    let b = Device::generic(&[1, 2], 64, 10, 42);
    let (Profile::Generic(a), Profile::Generic(b)) = (&a.profile, &b.profile) else {
        unreachable!()
    };
    assert_eq!(a.units[&2].discrete, b.units[&2].discrete);
    assert!(a.units[&1].discrete.iter().any(|&x| x) && a.units[&1].discrete.iter().any(|&x| !x));
}
