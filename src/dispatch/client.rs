//! Who a request comes from, as the dispatcher sees it: a master's id, where it is, what it may
//! do and address, how it talks, and its TLS identity; and the one description of a request
//! it makes (`Client::asking`).

use super::Table;
use crate::config::UnitSet;
use crate::master::{MasterId, Peer, Protocol, Rights};
use crate::routing::{Inbound, Target};
use std::net::SocketAddr;
use std::sync::Arc;

/// The master requests come from: one per connection.
#[derive(Debug)]
pub struct Client {
    pub master: MasterId,
    pub peer: Peer,
    pub rights: Rights,
    /// The unit ids it may address (its TLS role's `units`); `None`: any.
    pub units: Option<UnitSet>,
    /// Served before the others (`server.priority`).
    pub priority: bool,
    /// How it talks to the gateway: Modbus TCP unless [`Client::speaking`] says otherwise.
    pub protocol: Protocol,
    /// Whose share of a full bus queue its requests count against and whose turn on the line
    /// they take: its own, or one its listener gives all the masters of one source address
    /// (Modbus UDP).
    pub admission: MasterId,
    /// Who a TLS master's certificate says it is.
    pub identity: Option<Arc<Identity>>,
    /// The setting that limits its rights, as the journal names it (`server.read_only`,
    /// `server.tls.roles.NAME`); `None` while it may read and write.
    pub limited_by: Option<Arc<str>>,
}

/// A TLS master's certificate: its subject and the role it carries, as written.
#[derive(Debug)]
pub struct Identity {
    pub subject: String,
    pub role: Option<String>,
}

impl Client {
    pub fn new(master: MasterId, peer: SocketAddr, rights: Rights) -> Self {
        Self::at(master, Peer::Net(peer), rights)
    }

    /// A master at `peer`, a socket address or a serial master port.
    pub(crate) fn at(master: MasterId, peer: Peer, rights: Rights) -> Self {
        Client {
            master,
            peer,
            rights,
            units: None,
            priority: false,
            protocol: Protocol::Tcp,
            admission: master,
            identity: None,
            limited_by: (rights < Rights::ReadWrite).then(|| Arc::from("server.read_only")),
        }
    }

    /// The same master, speaking `protocol`.
    pub fn speaking(self, protocol: Protocol) -> Self {
        Client { protocol, ..self }
    }

    /// The same master, served before the others if `priority`.
    pub(crate) fn prioritised(self, priority: bool) -> Self {
        Client { priority, ..self }
    }

    /// The same master, allowed to address `units` only (`None`: any).
    pub(crate) fn addressing(self, units: Option<UnitSet>) -> Self {
        Client { units, ..self }
    }

    /// The same master, with its certificate's `identity`, its rights narrowed to `role_rights`
    /// by the role `role_key` names (`server.tls.roles.NAME` or
    /// `server.tls.default_role_access`).
    pub(crate) fn identified(
        self,
        identity: Identity,
        role_rights: Rights,
        role_key: String,
        role_units: bool,
    ) -> Self {
        let limited_by = match self.limited_by {
            Some(by) if self.rights <= role_rights => Some(by),
            _ if role_rights < Rights::ReadWrite || role_units => Some(Arc::from(role_key)),
            by => by,
        };
        Client {
            rights: self.rights.min(role_rights),
            identity: Some(Arc::new(identity)),
            limited_by,
            ..self
        }
    }

    pub(super) fn role(&self) -> Option<&str> {
        self.identity.as_ref().and_then(|i| i.role.as_deref())
    }

    /// Its request `pdu` to `unit`, going to `target` of `table`'s buses or to the virtual unit
    /// named `virtual_unit`, described once.
    pub(super) fn asking<'a>(
        &'a self,
        table: &'a Table,
        unit: u8,
        target: Option<Target>,
        virtual_unit: Option<&'a str>,
        pdu: &'a [u8],
    ) -> Inbound<'a> {
        Inbound {
            peer: &self.peer,
            protocol: self.protocol,
            subject: self.identity.as_ref().map(|i| i.subject.as_str()),
            role: self.role(),
            unit,
            bus: target.map(|t| table.buses[t.bus].name()),
            target,
            virtual_unit,
            pdu,
        }
    }
}
