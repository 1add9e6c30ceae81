//! The documentation says what the code has: every configuration key is in the configuration
//! reference (docs/configuration.md), every metric in docs/monitoring.md; every link between
//! the README and the docs/ pages leads to a file and a heading that exist; and every demo the
//! README runs is in the package. `readme` runs the README's walkthroughs.

mod defaults;
mod paths;
mod readme;

use modbus_gateway::Config;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

fn page(path: &str) -> String {
    std::fs::read_to_string(Path::new(ROOT).join(path)).unwrap_or_else(|e| panic!("{path}: {e}"))
}

#[test]
fn every_configuration_key_is_documented_in_the_configuration_reference() {
    // Every optional table present, so that the printed configuration has every key.
    let config = Config::from_toml_str(
        "[server]\nlisten_rtu_over_tcp = \"127.0.0.1:1\"\nlisten_udp = \"127.0.0.1:1\"\n\
         listen_tls = \"127.0.0.1:2\"\nallow = \"10.0.0.0/8\"\nread_only = \"10.1.0.0/16\"\n\
         priority = \"10.2.0.0/16\"\n\
         [server.tls]\ncertificate = \"a\"\nprivate_key = \"b\"\nclient_ca = \"c\"\ncrl = \"d\"\n\
         roles = { viewer = \"read_only\" }\n\
         [[server.serial]]\nname = \"p\"\ndevice = \"/dev/ttyS9\"\nbyte_timeout = \"5ms\"\n\
         latency_timer = \"1ms\"\n\
         [[bus]]\nname = \"a\"\ndevice = \"sim\"\nmode = \"listen\"\nmax_age = \"5s\"\n\
         [bus.sim_master]\npause = \"1ms\"\nresponse_timeout = \"200ms\"\n\
         [[bus.sim_master.read]]\nslave = 1\ntable = \"input\"\nregister = 0\ncount = 2\n\
         [[bus.sim_slave]]\naddress = 1\n\
         [[bus]]\nname = \"b\"\ndevice = \"/dev/ttyS1\"\nlatency_timer = \"1ms\"\n\
         [bus.rs485]\nmode = \"kernel\"\nrts_on_send = false\nrts_after_send = true\n\
         delay_before_send = \"1ms\"\ndelay_after_send = \"1ms\"\nrx_during_tx = true\n\
         echo = true\n\
         [[bus.slave]]\naddress = 1\ncoalesce_reads = false\ncache = \"1s\"\n\
         template = \"eastron-sdm120\"\n\
         [[bus.slave.value]]\nname = \"setpoint\"\nregister = 0x2001\ndeadband = 0.5\n\
         writable = true\n\
         [[bus]]\nname = \"c\"\ndevice = \"tcp://h:1\"\npacking_delay = \"10ms\"\n\
         connect_delay = \"1s\"\n\
         [[bus]]\nname = \"d\"\ndevice = \"tls://h:2\"\nframing = \"tcp\"\n\
         match_transaction_id = false\n\
         [bus.tls]\ncertificate = \"e\"\nprivate_key = \"f\"\nca = \"g\"\nserver_name = \"h\"\n\
         [[bus]]\nname = \"e\"\ndevice = \"tcp://h:3\"\nframing = \"tcp\"\nmax_in_flight = 4\n\
         [[route]]\nunits = \"255\"\nbus = \"a\"\naddress = 1\n\
         [[rule]]\nname = \"r\"\nmasters = \"10.3.0.0/16\"\nroles = \"viewer\"\n\
         protocols = \"tls\"\nbuses = \"a\"\nunits = \"1-4\"\nfunctions = \"write\"\n\
         registers = \"0x2000-0x2001\"\naction = \"deny\"\n\
         [audit]\npath = \"w.jsonl\"\nmax_size = \"1MiB\"\nkeep = 2\non_error = \"allow\"\n\
         fsync = true\n\
         [[virtual]]\nunit = 200\nname = \"copy\"\ntemplate = \"eastron-sdm630\"\n\
         source = { bus = \"b\", slave = 1 }\nmax_age = \"10s\"\n\
         [[virtual.register]]\nregister = 0x1000\ntable = \"holding\"\nvalue = \"setpoint\"\n\
         type = \"f32\"\nword_order = \"little\"\nbyte_order = \"little\"\nscale = 0.01\n\
         offset = 1\nwritable = true\n\
         [mqtt]\nurl = \"mqtt://127.0.0.1\"\nclient_id = \"gw\"\nusername = \"u\"\n\
         topic_prefix = \"p\"\nqos = 0\nretain = false\npublish_interval = \"10s\"\n\
         home_assistant = true\ndiscovery_prefix = \"ha\"\nwrites = true\n",
    )
    .expect("a valid configuration");
    let printed = config.to_toml();
    let keys: BTreeSet<&str> = printed
        .lines()
        .filter_map(|line| line.split_once(" = ").map(|(key, _)| key.trim()))
        // Entries of the roles table are the user's names, not keys.
        .filter(|key| *key != "viewer")
        .collect();
    assert!(
        keys.len() > 40 && keys.contains("discovery_prefix"),
        "{keys:?}"
    );
    let reference = page("docs/configuration.md");
    // [mqtt]'s files must be there and readable for the check: named here instead.
    let keys: BTreeSet<&str> = keys
        .into_iter()
        .chain(["password_file", "ca_file", "cert_file", "key_file"])
        .collect();
    let missing: Vec<&&str> = keys
        .iter()
        .filter(|key| !reference.contains(&format!("`{key}`")))
        .collect();
    assert!(
        missing.is_empty(),
        "keys docs/configuration.md does not name: {missing:?}"
    );
}

#[test]
fn every_metric_is_documented_in_the_monitoring_page() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/src/metrics");
    let mut names = BTreeSet::new();
    // Every source file under src/metrics, its folders' too.
    let mut files = Vec::new();
    let mut folders = vec![std::path::PathBuf::from(dir)];
    while let Some(folder) = folders.pop() {
        for entry in std::fs::read_dir(folder).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                folders.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                files.push(path);
            }
        }
    }
    for path in files {
        let source = std::fs::read_to_string(path).unwrap();
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
    let monitoring = page("docs/monitoring.md");
    let missing: Vec<&String> = names
        .iter()
        .filter(|name| !monitoring.contains(&format!("`{name}`")))
        .collect();
    assert!(
        missing.is_empty(),
        "metrics docs/monitoring.md does not document: {missing:?}"
    );
}

/// GitHub's anchor for a heading: lowercase, punctuation other than `-` and `_` dropped, spaces
/// as `-`.
fn anchor(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter(|c| c.is_alphanumeric() || matches!(c, '-' | '_' | ' '))
        .map(|c| if c == ' ' { '-' } else { c })
        .collect()
}

/// The anchors of a Markdown file's headings (outside fenced blocks).
fn anchors(text: &str) -> BTreeSet<String> {
    let mut fenced = false;
    let mut found = BTreeSet::new();
    for line in text.lines() {
        if line.starts_with("```") {
            fenced = !fenced;
        } else if !fenced && line.starts_with('#') {
            found.insert(anchor(line.trim_start_matches('#')));
        }
    }
    found
}

/// The targets of a Markdown text's inline links `[text](target)`.
fn links(text: &str) -> Vec<String> {
    text.split("](")
        .skip(1)
        .filter_map(|rest| rest.split_once(')').map(|(target, _)| target.to_owned()))
        .collect()
}

#[test]
fn every_link_between_the_readme_and_the_docs_pages_leads_somewhere() {
    let mut files: Vec<PathBuf> = vec![Path::new(ROOT).join("README.md")];
    for entry in std::fs::read_dir(Path::new(ROOT).join("docs")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "md") {
            files.push(path);
        }
    }
    assert!(files.len() > 8, "the reference is in docs/: {files:?}");
    let mut checked = 0;
    for file in &files {
        let text = std::fs::read_to_string(file).unwrap();
        for target in links(&text) {
            if target.starts_with("http") || target.contains(' ') {
                continue;
            }
            let (path, fragment) = target.split_once('#').unwrap_or((&target, ""));
            let linked = if path.is_empty() {
                file.clone()
            } else {
                file.parent().unwrap().join(path)
            };
            assert!(
                linked.exists(),
                "{}: the link to {target} leads to no file",
                file.display()
            );
            if !fragment.is_empty() {
                let headings = anchors(&std::fs::read_to_string(&linked).unwrap());
                assert!(
                    headings.contains(fragment),
                    "{}: the link to {target} names no heading there",
                    file.display()
                );
            }
            checked += 1;
        }
    }
    assert!(checked > 20, "only {checked} links");
}

#[test]
fn the_readme_links_every_docs_page() {
    let readme = page("README.md");
    for entry in std::fs::read_dir(Path::new(ROOT).join("docs")).unwrap() {
        let name = entry.unwrap().file_name().into_string().unwrap();
        if name.ends_with(".md") {
            assert!(
                readme.contains(&format!("](docs/{name})")),
                "README.md does not link docs/{name}"
            );
        }
    }
}

/// config/gateway.toml with every commented `key = value` line and table header uncommented,
/// but for the tables this file's bus or machine cannot take: `[server.tls]` (its files are not
/// here, and `listen_tls` needs them) and `[[bus.sim_slave]]` (only on a `device = "sim"` bus),
/// the route's `address`, the alternative to its `offset`, and the rule's `roles` (which needs
/// `[server.tls]`).
fn gateway_toml_uncommented() -> String {
    let mut skipping = false;
    let mut out = String::new();
    for line in page("config/gateway.toml").lines() {
        if line.starts_with("#[") || line.starts_with('[') {
            skipping = line == "#[server.tls]" || line == "#[[bus.sim_slave]]";
        }
        let commented_setting = line.starts_with("#[")
            || line
                .strip_prefix('#')
                .and_then(|rest| rest.split_once(" = "))
                .is_some_and(|(key, _)| key.chars().all(|c| c.is_ascii_lowercase() || c == '_'));
        let excepted = line.starts_with("#address = 17")
            || line.starts_with("#listen_tls = ")
            || line.starts_with("#roles = [");
        if commented_setting && !skipping && !excepted {
            out.push_str(&line[1..]);
        } else {
            out.push_str(line);
        }
        out.push('\n');
    }
    out
}

#[test]
fn every_commented_default_of_the_installed_config_can_be_uncommented() {
    let text = gateway_toml_uncommented();
    assert!(text.contains("\n[bus.rs485]\nmode = \"off\"\n"), "{text}");
    assert!(text.contains("\nrts_on_send = true\nrts_after_send = false\n"));
    if let Err(errors) = Config::from_toml_str(&text) {
        panic!("config/gateway.toml, every default uncommented: {errors}\n{text}");
    }
}

#[test]
fn the_security_pages_toml_excerpt_is_a_verbatim_part_of_the_tls_demo() {
    let security = page("docs/security.md");
    let demo = page("config/demo-tls.toml");
    let excerpts: Vec<&str> = security
        .split("```toml\n")
        .skip(1)
        .filter_map(|rest| rest.split_once("```").map(|(toml, _)| toml))
        .collect();
    assert!(!excerpts.is_empty(), "docs/security.md has no TOML excerpt");
    for excerpt in excerpts {
        assert!(
            demo.contains(excerpt),
            "docs/security.md shows what config/demo-tls.toml does not have:\n{excerpt}"
        );
    }
}

#[test]
fn every_demo_configuration_is_in_the_package_and_checked_there() {
    let manifest: toml::Value = toml::from_str(&page("Cargo.toml")).expect("Cargo.toml");
    let assets = manifest["package"]["metadata"]["deb"]["assets"]
        .as_array()
        .expect("the package's assets");
    let shipped: BTreeSet<(&str, &str)> = assets
        .iter()
        .filter_map(|asset| Some((asset[0].as_str()?, asset[1].as_str()?)))
        .collect();
    let check = page(".ci/check-package");
    let mut demos = 0;
    for entry in std::fs::read_dir(Path::new(ROOT).join("config")).unwrap() {
        let name = entry.unwrap().file_name().into_string().unwrap();
        if !(name.starts_with("demo") && name.ends_with(".toml")) {
            continue;
        }
        let installed = format!("usr/share/doc/modbus-gateway/{name}");
        assert!(
            shipped.contains(&(format!("config/{name}").as_str(), installed.as_str())),
            "Cargo.toml's package assets do not install config/{name} as {installed}"
        );
        assert!(
            check.contains(&format!("expect_file -rw-r--r-- {installed}\n")),
            ".ci/check-package does not look for {installed}"
        );
        demos += 1;
    }
    // demo, demo-ascii, demo-device-server, demo-serial, demo-tls, demo-writes.
    assert!(demos >= 6, "only {demos} demos in config/");
}

/// The `toml` blocks of `text`, in order.
fn toml_blocks(text: &str) -> Vec<String> {
    let mut blocks = Vec::new();
    let mut lines = text.lines();
    while lines.by_ref().any(|line| line == "```toml") {
        let block: Vec<&str> = lines.by_ref().take_while(|line| *line != "```").collect();
        blocks.push(block.join("\n") + "\n");
    }
    blocks
}

#[test]
fn the_serial_ports_pages_split_bus_and_its_rules_load_as_written() {
    let text = page("docs/serial-ports.md");
    let blocks = toml_blocks(&text);
    assert_eq!(blocks.len(), 3, "{blocks:?}");
    // The split bus, with the page's two rules for the port's master.
    let config = format!("{}\n{}", blocks[1], blocks[2]);
    let config =
        Config::from_toml_str(&config).unwrap_or_else(|errors| panic!("{errors:?}\n{config}"));
    assert_eq!(config.server.serial.len(), 1);
    assert!(config.server.serial[0].priority);
    // The page's opening example is a port's whole section.
    let port = crate::support::GatewayConfig::new()
        .server_table(&blocks[0])
        .bus(crate::support::sim_line())
        .to_toml();
    Config::from_toml_str(&port).unwrap_or_else(|errors| panic!("{errors:?}\n{port}"));
}

#[test]
fn the_virtual_units_pages_examples_load_as_written() {
    let text = page("docs/virtual-units.md");
    let blocks = toml_blocks(&text);
    assert_eq!(blocks.len(), 3, "{blocks:?}");
    let load = |config: String| {
        Config::from_toml_str(&config).unwrap_or_else(|errors| panic!("{errors}\n{config}"))
    };
    // The opening example: registers of the demo's drives.
    let demo = |slaves: &str| {
        crate::support::GatewayConfig::new()
            .bus(crate::support::Bus::sim("demo").text(slaves))
            .to_toml()
    };
    let drives = demo(
        "[[bus.slave]]\naddress = 1\ntemplate = \"goodrive20\"\n\
         [[bus.slave]]\naddress = 2\ntemplate = \"goodrive300\"\n",
    );
    let config = load(format!("{drives}{}", blocks[0]));
    assert_eq!(config.virtual_units[0].register.len(), 2);
    // The SDM120 presented as an SDM630: a whole configuration.
    let config = load(blocks[1].clone());
    let meter = &config.virtual_units[0];
    assert_eq!(
        (meter.unit, meter.template.as_deref()),
        (200, Some("eastron-sdm630"))
    );
    // The writable setpoint, under the demo's slave 2.
    let slave = demo("[[bus.slave]]\naddress = 2\n");
    let config = load(format!("{slave}{}", blocks[2]));
    assert!(config.virtual_units[0].register[0].writable);
}
