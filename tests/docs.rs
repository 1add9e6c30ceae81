//! The README and docs/*.md document what the code has: every configuration key and every
//! metric.

use modbus_gateway::Config;
use std::collections::BTreeSet;

/// The README and the pages under docs/, as one text.
fn readme() -> String {
    let root = env!("CARGO_MANIFEST_DIR");
    let mut text = std::fs::read_to_string(format!("{root}/README.md")).unwrap();
    if let Ok(pages) = std::fs::read_dir(format!("{root}/docs")) {
        for page in pages {
            let path = page.unwrap().path();
            if path.extension().is_some_and(|e| e == "md") {
                text.push_str(&std::fs::read_to_string(path).unwrap());
            }
        }
    }
    text
}

#[test]
fn every_configuration_key_is_documented_in_the_readme() {
    // Every optional table present, so that the printed configuration has every key.
    let config = Config::from_toml_str(
        "[server]\nlisten_rtu_over_tcp = \"127.0.0.1:1\"\nlisten_udp = \"127.0.0.1:1\"\n\
         listen_tls = \"127.0.0.1:2\"\nallow = \"10.0.0.0/8\"\nread_only = \"10.1.0.0/16\"\n\
         priority = \"10.2.0.0/16\"\n\
         [server.tls]\ncertificate = \"a\"\nprivate_key = \"b\"\nclient_ca = \"c\"\ncrl = \"d\"\n\
         roles = { viewer = \"read_only\" }\n\
         [[bus]]\nname = \"a\"\ndevice = \"sim\"\n\
         [[bus.slave]]\naddress = 1\ncoalesce_reads = false\ncache = \"1s\"\n\
         [[bus.sim_slave]]\naddress = 1\n\
         [[route]]\nunits = \"255\"\nbus = \"a\"\naddress = 1\n",
    )
    .expect("a valid configuration");
    let printed = config.to_toml();
    let keys: BTreeSet<&str> = printed
        .lines()
        .filter_map(|line| line.split_once(" = ").map(|(key, _)| key.trim()))
        // Entries of the roles table are the user's names, not keys.
        .filter(|key| *key != "viewer")
        .collect();
    assert!(keys.len() > 40, "{keys:?}");
    let readme = readme();
    let missing: Vec<&&str> = keys
        .iter()
        .filter(|key| !readme.contains(&format!("`{key}`")))
        .collect();
    assert!(
        missing.is_empty(),
        "keys the README does not name: {missing:?}"
    );
}

#[test]
fn every_metric_is_documented_in_the_readme() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/src/metrics");
    let mut names = BTreeSet::new();
    for entry in std::fs::read_dir(dir).unwrap() {
        let source = std::fs::read_to_string(entry.unwrap().path()).unwrap();
        for piece in source.split('"').skip(1).step_by(2) {
            if piece.starts_with("modbus_gateway_")
                && piece
                    .bytes()
                    .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_')
            {
                names.insert(piece.to_owned());
            }
        }
    }
    assert!(names.len() > 20, "{names:?}");
    let readme = readme();
    let missing: Vec<&String> = names
        .iter()
        .filter(|name| !readme.contains(&format!("`{name}`")))
        .collect();
    assert!(
        missing.is_empty(),
        "metrics the README does not document: {missing:?}"
    );
}
