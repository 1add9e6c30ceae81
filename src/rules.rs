//! Which `[[rule]]` decides a request, and what it decides: a pure table, like `routing`, built
//! from the configuration and replaced whole on a reload. Knows who sent a request, where it
//! goes and what its bytes ask; knows nothing of sessions, queues or the journal.
//!
//! A rule matches when every match key it gives matches. `units` names slaves, not unit ids: the
//! unit ids it lists are resolved through the routes once, when the table is built, and a request
//! matches by the slave it reaches, whichever unit id it used; a broadcast reaches every slave of
//! its bus. `units` and `registers` are the keys whose meaning follows the action: a `deny` or
//! `acknowledge` rule matches a request that touches any of its addresses (overlapping is enough),
//! while an `allow` rule matches only a request that touches none but its addresses, so that a
//! write running past an allowed range is not let through by it. A request whose addresses its
//! bytes cannot tell (a user-defined code, a file record) may touch any: it matches every `deny`
//! and `acknowledge` rule with registers and no `allow` rule with registers. Likewise a broadcast
//! matches every `deny` and `acknowledge` rule naming a slave of its bus, and only the `allow`
//! rules naming the broadcast itself.

use crate::config::{Action, Functions, Registers, Rule, UnitSet};
use crate::line::BROADCAST;
use crate::pdu::{self, ExceptionCode, Span, Touches};
use crate::routing::{Inbound, Router, Target};

/// What the rules decide for a request.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Decision {
    /// The deciding rule's place in the list; `None`: no rule matched, and the request goes.
    pub(crate) rule: Option<usize>,
    pub(crate) action: Action,
}

impl Decision {
    /// The exception a `deny` answers with: 0x02 when the rule names registers (the
    /// addresses are what is refused), 0x01 when it is about anything else.
    pub(crate) fn exception(&self, rules: &Rules) -> ExceptionCode {
        match self.rule.map(|at| &rules.list[at]) {
            Some(rule) if !rule.registers.is_empty() => ExceptionCode::IllegalDataAddress,
            _ => ExceptionCode::IllegalFunction,
        }
    }
}

/// The rules in force, in their order.
#[derive(Clone, Debug, Default)]
pub(crate) struct Rules {
    list: Vec<Rule>,
    names: Vec<String>,
    /// Each rule's `units` as the slaves they reach; `None` for a rule without `units`.
    slaves: Vec<Option<Reach>>,
}

/// The slaves some unit ids reach through the routes: for each bus, by its index, the
/// addresses there (the broadcast address among them when a unit routes to it), and the virtual
/// units among them.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub(crate) struct Reach(Vec<UnitSet>, UnitSet);

impl Reach {
    /// Where `units` go by `router`: a unit with no route reaches nothing.
    pub(crate) fn of(units: UnitSet, router: &Router) -> Reach {
        let mut buses: Vec<UnitSet> = Vec::new();
        for target in units.iter().filter_map(|unit| router.resolve(unit)) {
            if buses.len() <= target.bus {
                buses.resize(target.bus + 1, UnitSet::default());
            }
            buses[target.bus].insert(target.address);
        }
        let mut virtuals = UnitSet::default();
        for unit in units.iter().filter(|&u| router.virtuals().contains(u)) {
            virtuals.insert(unit);
        }
        Reach(buses, virtuals)
    }

    /// The virtual units among them.
    pub(crate) fn virtual_units(&self) -> UnitSet {
        self.1
    }

    /// The addresses reached on each bus that any are, by bus index.
    pub(crate) fn by_bus(&self) -> impl Iterator<Item = (usize, UnitSet)> + '_ {
        self.0
            .iter()
            .enumerate()
            .filter(|(_, addresses)| !addresses.is_empty())
            .map(|(bus, addresses)| (bus, *addresses))
    }

    /// Whether a request to `target` is about these slaves: it reaches one of them (a
    /// broadcast reaches every slave of its bus), or, for an `allow` rule, nothing else (a
    /// broadcast only when the broadcast itself is among them).
    fn hold(&self, target: Target, action: Action) -> bool {
        let Some(here) = self.0.get(target.bus) else {
            return false;
        };
        match (target.broadcast, action) {
            (true, Action::Allow) => here.contains(BROADCAST),
            (true, Action::Deny | Action::Acknowledge) => !here.is_empty(),
            (false, _) => here.contains(target.address),
        }
    }
}

impl Rules {
    /// `list` in force, its `units` reaching the slaves `router` routes them to.
    pub(crate) fn new(list: &[Rule], router: &Router) -> Rules {
        Rules {
            names: list
                .iter()
                .enumerate()
                .map(|(at, rule)| rule.display_name(at))
                .collect(),
            slaves: list
                .iter()
                .map(|rule| rule.units.map(|units| Reach::of(units, router)))
                .collect(),
            list: list.to_vec(),
        }
    }

    /// What the journal calls the rule at `at`.
    pub(crate) fn name(&self, at: usize) -> &str {
        &self.names[at]
    }

    /// The first rule that matches `asked`, and its action; none: allowed.
    pub(crate) fn decide(&self, asked: &Inbound<'_>) -> Decision {
        // What the request touches is read once, and only if a rule asks.
        let mut touches = None;
        let found = self
            .list
            .iter()
            .zip(&self.slaves)
            .position(|(rule, slaves)| {
                matches(rule, slaves.as_ref(), asked, || {
                    *touches.get_or_insert_with(|| pdu::touches(asked.pdu))
                })
            });
        Decision {
            rule: found,
            action: found.map_or(Action::Allow, |at| self.list[at].action),
        }
    }
}

fn matches(
    rule: &Rule,
    slaves: Option<&Reach>,
    asked: &Inbound<'_>,
    touches: impl FnOnce() -> Touches,
) -> bool {
    // A dual-stack listener sees IPv4 masters as ::ffff:a.b.c.d; rules name them as IPv4.
    // A serial port's master has no address: a rule naming `masters` is not about it.
    let peer = asked.peer.ip();
    let any = |empty: bool, found: bool| empty || found;
    any(
        rule.masters.is_empty(),
        peer.is_some_and(|ip| rule.masters.iter().any(|net| net.contains(&ip))),
    ) && any(
        rule.roles.is_empty(),
        asked
            .role
            .is_some_and(|role| rule.roles.iter().any(|r| r == role)),
    ) && any(
        rule.protocols.is_empty(),
        rule.protocols.contains(&asked.protocol),
    ) && any(
        rule.buses.is_empty(),
        asked
            .bus
            .is_some_and(|bus| rule.buses.iter().any(|b| b == bus)),
    ) && slaves.is_none_or(|slaves| match asked.target {
        Some(target) => slaves.hold(target, rule.action),
        // A virtual unit is a slave of the gateway's: its unit id names it.
        None => asked.virtual_unit.is_some() && slaves.1.contains(asked.unit),
    }) && any(
        rule.functions.is_empty(),
        rule.functions
            .iter()
            .any(|f| function_matches(*f, asked.pdu)),
    ) && (rule.registers.is_empty() || registers_match(rule, touches()))
}

fn function_matches(functions: Functions, pdu: &[u8]) -> bool {
    let code = pdu.first().copied().unwrap_or(0);
    match functions {
        Functions::Code(wanted) => code == wanted,
        Functions::Read => pdu::is_read_only(pdu),
        Functions::Write => !pdu::is_read_only(pdu),
        Functions::Diagnostic => pdu::is_diagnostic(code),
        Functions::DiagnosticWrite => pdu::is_diagnostic(code) && !pdu::is_read_only(pdu),
    }
}

fn registers_match(rule: &Rule, touches: Touches) -> bool {
    let ranges = &rule.registers;
    let spans = match touches {
        Touches::Nothing => return false,
        Touches::Unknown => return rule.action != Action::Allow,
        Touches::Spans(first, second) => [Some(first), second],
    };
    let spans = spans.into_iter().flatten();
    if rule.action == Action::Allow {
        spans.into_iter().all(|span| within(ranges, span))
    } else {
        spans.into_iter().any(|span| overlaps(ranges, span))
    }
}

fn overlaps(ranges: &[Registers], span: Span) -> bool {
    let last = u16::try_from(span.last).unwrap_or(u16::MAX);
    ranges.iter().any(|r| r.overlaps(span.first, last))
}

/// Every address of `span` is in one of `ranges` (which may adjoin).
fn within(ranges: &[Registers], span: Span) -> bool {
    let mut next = u32::from(span.first);
    while next <= span.last {
        let holding = ranges
            .iter()
            .filter(|r| u32::from(r.first) <= next && next <= u32::from(r.last))
            .map(|r| u32::from(r.last))
            .max();
        match holding {
            Some(last) => next = last + 1,
            None => return false,
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{Config, UnitSet};
    use crate::master::{Peer, Protocol};

    const LINE1: &str = "[[bus]]\nname = \"line1\"\ndevice = \"sim\"\n";

    fn config(toml: &str) -> Config {
        Config::from_toml_str(&format!("{LINE1}{toml}")).expect("valid rules")
    }

    fn rules(toml: &str) -> Rules {
        let config = config(toml);
        Rules::new(&config.rule, &Router::new(&config))
    }

    /// Slave `address` of bus 0, a serial line (where 0 is the broadcast).
    fn slave(address: u8) -> Option<Target> {
        Some(Target {
            bus: 0,
            address,
            broadcast: address == BROADCAST,
        })
    }

    /// A master at `addr`, for as long as the test runs.
    fn peer_at(addr: &str) -> &'static Peer {
        Box::leak(Box::new(Peer::Net(addr.parse().unwrap())))
    }

    fn asked(pdu: &[u8]) -> Inbound<'_> {
        Inbound {
            peer: peer_at("192.168.20.5:40000"),
            protocol: Protocol::Tcp,
            subject: None,
            role: None,
            unit: 3,
            bus: Some("line1"),
            target: slave(3),
            virtual_unit: None,
            pdu,
        }
    }

    const WRITE_2000: [u8; 5] = [0x06, 0x20, 0x00, 0x00, 0x05];
    const WRITE_1FFF_2001: [u8; 12] = [0x10, 0x1F, 0xFF, 0, 3, 6, 0, 1, 0, 2, 0, 3];
    const READ_2000: [u8; 5] = [0x03, 0x20, 0x00, 0x00, 0x02];

    #[test]
    fn the_first_matching_rule_decides_and_no_match_allows() {
        let rules = rules(
            r#"
            [[rule]]
            name = "wallbox"
            registers = "0x2000-0x2001"
            functions = "write"
            action = "allow"
            [[rule]]
            functions = "write"
            action = "deny"
            "#,
        );
        let decided = rules.decide(&asked(&WRITE_2000));
        assert_eq!((decided.rule, decided.action), (Some(0), Action::Allow));
        assert_eq!(rules.name(0), "wallbox");
        let other = [0x06, 0x30, 0x00, 0x00, 0x05];
        let decided = rules.decide(&asked(&other));
        assert_eq!((decided.rule, decided.action), (Some(1), Action::Deny));
        assert_eq!(decided.exception(&rules), ExceptionCode::IllegalFunction);
        assert_eq!(rules.name(1), "rule 2");
        let decided = rules.decide(&asked(&READ_2000));
        assert_eq!((decided.rule, decided.action), (None, Action::Allow));
    }

    /// An allow rule covers only requests within its registers; a deny rule any that overlaps.
    #[test]
    fn an_allow_covers_requests_within_its_registers_a_deny_any_that_overlaps() {
        let rules = rules(
            r#"
            [[rule]]
            registers = ["0x2000", "0x2001"]
            action = "allow"
            [[rule]]
            registers = "0x2000-0x2001"
            action = "deny"
            "#,
        );
        // Adjoining ranges hold a two-register write between them.
        let both = [0x10, 0x20, 0x00, 0, 2, 4, 0, 1, 0, 2];
        assert_eq!(rules.decide(&asked(&both)).rule, Some(0));
        // Running over the allowed range from below: not allowed by it, denied by the second.
        let decided = rules.decide(&asked(&WRITE_1FFF_2001));
        assert_eq!((decided.rule, decided.action), (Some(1), Action::Deny));
        assert_eq!(decided.exception(&rules), ExceptionCode::IllegalDataAddress);
        // A read of 0x2000 writing 0x0000: its write is outside the allowed range.
        let hidden = [0x17, 0x20, 0x00, 0, 1, 0x00, 0x00, 0, 1, 2, 0xAB, 0xCD];
        assert_eq!(rules.decide(&asked(&hidden)).rule, Some(1));
        // A user-defined code may touch anything: denied, never allowed by registers.
        assert_eq!(rules.decide(&asked(&[0x41, 0x20, 0x00])).rule, Some(1));
        // Diagnostics touch no register.
        assert_eq!(rules.decide(&asked(&[0x08, 0, 1, 0, 0])).rule, None);
        // A span past 65535 is not cut short into an allowed range.
        let rules = super::tests::rules("[[rule]]\nregisters = \"0xFFFF\"\naction = \"allow\"\n");
        let past = [0x10, 0xFF, 0xFF, 0, 2, 4, 0, 1, 0, 2];
        assert_eq!(rules.decide(&asked(&past)).rule, None);
    }

    #[test]
    fn each_match_key_must_match() {
        let rules = rules(
            r#"
            [[rule]]
            masters = "192.168.20.0/24"
            protocols = "udp"
            buses = "line1"
            units = "1-4"
            functions = [6]
            action = "deny"
            "#,
        );
        let base = Inbound {
            protocol: Protocol::Udp,
            ..asked(&WRITE_2000)
        };
        assert_eq!(rules.decide(&base).rule, Some(0));
        let misses = [
            Inbound {
                peer: peer_at("192.168.21.5:40000"),
                ..base
            },
            Inbound {
                protocol: Protocol::Tcp,
                ..base
            },
            Inbound { bus: None, ..base },
            Inbound {
                target: slave(5),
                ..base
            },
            Inbound {
                pdu: &WRITE_1FFF_2001,
                ..base
            },
        ];
        for miss in misses {
            assert_eq!(rules.decide(&miss).rule, None, "{miss:?}");
        }
        let mapped = Inbound {
            peer: peer_at("[::ffff:192.168.20.5]:40000"),
            ..base
        };
        assert_eq!(
            rules.decide(&mapped).rule,
            Some(0),
            "IPv4 on a dual-stack listener"
        );
    }

    #[test]
    fn roles_match_tls_masters_by_the_role_their_certificate_carries() {
        let list = vec![Rule {
            name: None,
            masters: Vec::new(),
            roles: vec!["operator".into()],
            protocols: Vec::new(),
            buses: Vec::new(),
            units: Some("10-19".parse::<UnitSet>().unwrap()),
            functions: vec![Functions::Write],
            registers: Vec::new(),
            action: Action::Acknowledge,
        }];
        let rules = Rules::new(&list, &Router::new(&config("")));
        let operator = Inbound {
            role: Some("operator"),
            target: slave(12),
            ..asked(&WRITE_2000)
        };
        assert_eq!(rules.decide(&operator).action, Action::Acknowledge);
        assert_eq!(
            rules
                .decide(&Inbound {
                    role: None,
                    ..operator
                })
                .rule,
            None
        );
        assert_eq!(
            rules
                .decide(&Inbound {
                    pdu: &READ_2000,
                    ..operator
                })
                .rule,
            None
        );
        let diagnostic = rules_with_diagnostic();
        assert_eq!(diagnostic.decide(&asked(&[0x2B, 0x0E, 1, 0])).rule, Some(0));
        assert_eq!(diagnostic.decide(&asked(&READ_2000)).rule, None);
    }

    /// The drive-parameters rule of docs/writes.md on a line whose unit 200 is the broadcast
    /// and whose units 101-104 are slaves 1-4.
    const ROUTED: &str = r#"
        [[route]]
        units = "200"
        bus = "line1"
        address = 0
        [[route]]
        units = "101-104"
        bus = "line1"
        offset = -100
    "#;

    /// The rule deciding `pdu` to each of `units`, routed as `toml` says.
    fn deciding(toml: &str, pdu: &[u8], units: &[u8]) -> Vec<Option<usize>> {
        let config = config(toml);
        let router = Router::new(&config);
        let rules = Rules::new(&config.rule, &router);
        let to = |&unit: &u8| Inbound {
            target: router.resolve(unit),
            ..asked(pdu)
        };
        units
            .iter()
            .map(|unit| rules.decide(&to(unit)).rule)
            .collect()
    }

    #[test]
    fn a_units_rule_holds_its_slaves_by_any_unit_id_and_by_broadcast() {
        let deny = "[[rule]]\nunits = \"1-4\"\nregisters = \"0x0000-0x1FFF\"\naction = \"deny\"\n";
        let write = [0x06, 0x00, 0x05, 0x00, 0x01];
        // Units 1, 0 (broadcast), 200 (routed to the broadcast), 101 (routed to slave 1).
        assert_eq!(
            deciding(&format!("{ROUTED}{deny}"), &write, &[1, 0, 200, 101]),
            [Some(0); 4]
        );
        // Slave 5 by its own id and by 105: not a slave the rule names.
        assert_eq!(
            deciding(&format!("{ROUTED}{deny}"), &write, &[5, 105]),
            [None; 2]
        );
        // Acknowledge rules take broadcasts the same way.
        let acknowledge = deny.replace("deny", "acknowledge");
        assert_eq!(
            deciding(&format!("{ROUTED}{acknowledge}"), &write, &[0, 200]),
            [Some(0); 2]
        );
        // A unit with no route names no slave: with two buses, unit 50 goes nowhere.
        let two = "[[bus]]\nname = \"line2\"\ndevice = \"sim\"\n[[route]]\nunits = \"1-4\"\nbus = \"line1\"\n\
                   [[rule]]\nunits = \"50\"\naction = \"deny\"\n";
        assert_eq!(deciding(two, &write, &[1, 2]), [None; 2]);
    }

    #[test]
    fn an_allow_rule_on_units_covers_a_broadcast_only_if_it_names_the_broadcast() {
        let write = [0x06, 0x00, 0x05, 0x00, 0x01];
        let allow = |units: &str| {
            format!("{ROUTED}[[rule]]\nunits = \"{units}\"\naction = \"allow\"\n[[rule]]\naction = \"deny\"\n")
        };
        // Slaves 1-4 by any id; a broadcast reaches the others too, so it is not theirs.
        assert_eq!(
            deciding(&allow("1-4"), &write, &[1, 101, 0, 200]),
            [Some(0), Some(0), Some(1), Some(1)]
        );
        // Naming unit 0, or a unit routed to it, names the broadcast: unit 200 and unit 0 alike.
        assert_eq!(
            deciding(&allow("200"), &write, &[0, 200, 1]),
            [Some(0), Some(0), Some(1)]
        );
        // A deny rule naming the broadcast alone refuses broadcasts, not the slaves one by one.
        let deny = format!("{ROUTED}[[rule]]\nunits = \"0\"\naction = \"deny\"\n");
        assert_eq!(
            deciding(&deny, &write, &[200, 0, 1]),
            [Some(0), Some(0), None]
        );
    }

    #[test]
    fn on_a_modbus_tcp_device_unit_0_is_a_slave_of_its_own_not_a_broadcast() {
        let device = "[[bus]]\nname = \"inverter\"\ndevice = \"tcp://127.0.0.1:502\"\n\
                      framing = \"tcp\"\n\
                      [[route]]\nunits = \"10\"\nbus = \"inverter\"\naddress = 0\n\
                      [[route]]\nunits = \"11\"\nbus = \"inverter\"\naddress = 5\n\
                      [[rule]]\nunits = \"11\"\naction = \"deny\"\n";
        let write = [0x06, 0x00, 0x05, 0x00, 0x01];
        // Unit 10 is the device's unit 0, one unit among others: the rule names unit 5 only.
        assert_eq!(deciding(device, &write, &[10, 11]), [None, Some(0)]);
    }

    #[test]
    fn diagnostic_write_takes_restarts_and_tunnels_but_not_the_diagnostics_that_read() {
        let rules = rules("[[rule]]\nfunctions = \"diagnostic_write\"\naction = \"deny\"\n");
        let denied = |pdu: &[u8]| rules.decide(&asked(pdu)).rule.is_some();
        // Restart communications, listen only, clear counters; a CANopen General Reference.
        assert!(denied(&[0x08, 0x00, 0x01, 0x00, 0x00]));
        assert!(denied(&[0x08, 0x00, 0x04, 0x00, 0x00]));
        assert!(denied(&[0x08, 0x00, 0x0A, 0x00, 0x00]));
        assert!(denied(&[0x2B, 0x0D, 0x00, 0x20, 0x00]));
        // Echo, a counter, Read Device Identification, Report Server ID; a write, a read.
        assert!(!denied(&[0x08, 0x00, 0x00, 0x12, 0x34]));
        assert!(!denied(&[0x08, 0x00, 0x0B, 0x00, 0x00]));
        assert!(!denied(&[0x2B, 0x0E, 0x01, 0x00]));
        assert!(!denied(&[0x11]));
        assert!(!denied(&WRITE_2000));
        assert!(!denied(&READ_2000));
    }

    fn rules_with_diagnostic() -> Rules {
        rules("[[rule]]\nfunctions = \"diagnostic\"\naction = \"deny\"\n")
    }
}
