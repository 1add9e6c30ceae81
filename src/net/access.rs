//! Who may connect (`server.allow`) and who may only read (`server.read_only`), decided from the
//! peer's address alone. Pure: knows nothing of sockets or sessions.

use crate::master::Rights;
use ipnet::IpNet;
use std::net::IpAddr;

#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub(crate) struct NetworkRights {
    /// Empty: anyone may connect.
    allow: Vec<IpNet>,
    read_only: Vec<IpNet>,
    priority: Vec<IpNet>,
}

impl NetworkRights {
    pub(crate) fn new(allow: Vec<IpNet>, read_only: Vec<IpNet>) -> Self {
        NetworkRights {
            allow,
            read_only,
            priority: Vec::new(),
        }
    }

    /// The same, with masters from `priority` served before the others.
    pub(crate) fn with_priority(self, priority: Vec<IpNet>) -> Self {
        NetworkRights { priority, ..self }
    }

    /// Whether a master from `peer` is in `server.priority`.
    pub(crate) fn is_priority(&self, peer: IpAddr) -> bool {
        let peer = peer.to_canonical();
        self.priority.iter().any(|net| net.contains(&peer))
    }

    /// The rights of a master connecting from `peer`, or `None` if it may not connect.
    pub(crate) fn admit(&self, peer: IpAddr) -> Option<Rights> {
        // A dual-stack listener sees IPv4 masters as ::ffff:a.b.c.d; the lists name them as IPv4.
        let peer = peer.to_canonical();
        let listed = |nets: &[IpNet]| nets.iter().any(|net| net.contains(&peer));
        if !self.allow.is_empty() && !listed(&self.allow) {
            return None;
        }
        Some(if listed(&self.read_only) {
            Rights::ReadOnly
        } else {
            Rights::ReadWrite
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn nets(list: &[&str]) -> Vec<IpNet> {
        list.iter().map(|n| n.parse().unwrap()).collect()
    }

    fn ip(text: &str) -> IpAddr {
        text.parse().unwrap()
    }

    #[test]
    fn with_no_lists_everyone_may_read_and_write() {
        let access = NetworkRights::default();
        assert_eq!(access.admit(ip("203.0.113.9")), Some(Rights::ReadWrite));
        assert_eq!(access.admit(ip("2001:db8::1")), Some(Rights::ReadWrite));
    }

    #[test]
    fn an_allow_list_refuses_everyone_outside_it() {
        let access = NetworkRights::new(nets(&["10.0.0.0/8", "2001:db8::/32"]), vec![]);
        assert_eq!(access.admit(ip("10.20.30.40")), Some(Rights::ReadWrite));
        assert_eq!(access.admit(ip("2001:db8:5::7")), Some(Rights::ReadWrite));
        assert_eq!(access.admit(ip("11.0.0.1")), None);
        assert_eq!(access.admit(ip("127.0.0.1")), None);
        assert_eq!(access.admit(ip("2001:db9::1")), None);
    }

    #[test]
    fn ipv4_masters_on_a_dual_stack_listener_match_ipv4_networks() {
        let access = NetworkRights::new(nets(&["192.168.1.0/24"]), nets(&["192.168.1.7/32"]));
        assert_eq!(
            access.admit(ip("::ffff:192.168.1.20")),
            Some(Rights::ReadWrite)
        );
        assert_eq!(
            access.admit(ip("::ffff:192.168.1.7")),
            Some(Rights::ReadOnly)
        );
        assert_eq!(access.admit(ip("::ffff:192.168.2.1")), None);
    }

    #[test]
    fn read_only_networks_may_connect_but_only_read() {
        let access = NetworkRights::new(vec![], nets(&["172.16.0.0/12"]));
        assert_eq!(access.admit(ip("172.16.4.4")), Some(Rights::ReadOnly));
        assert_eq!(access.admit(ip("172.32.0.1")), Some(Rights::ReadWrite));
    }

    #[test]
    fn priority_networks_are_told_apart_also_on_a_dual_stack_listener() {
        let access = NetworkRights::default().with_priority(nets(&["10.1.0.0/16"]));
        assert!(access.is_priority(ip("10.1.2.3")));
        assert!(access.is_priority(ip("::ffff:10.1.2.3")));
        assert!(!access.is_priority(ip("10.2.0.1")));
        assert_eq!(access.admit(ip("10.1.2.3")), Some(Rights::ReadWrite));
    }

    #[test]
    fn a_read_only_network_outside_the_allow_list_is_still_refused() {
        let access = NetworkRights::new(nets(&["10.0.0.0/8"]), nets(&["192.168.0.0/16"]));
        assert_eq!(access.admit(ip("192.168.1.1")), None);
    }
}
