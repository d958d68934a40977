"""CycloneDDS transport for the G1 topics: a domain bound to one network interface, and the
LowState / LowCmd endpoints.

The interface is chosen with an explicit CycloneDDS XML configuration passed to
``cyclonedds.domain.Domain`` (the same as setting ``CYCLONEDDS_URI``, but per domain, so two
domains in one process, e.g. in tests, can differ). On the loopback interface (``lo``), which
carries no multicast on Linux, discovery is unicast: multicast off, the peer 127.0.0.1 and
automatic participant indices (so up to ``MAX_LOCAL_PARTICIPANTS`` processes on one host find
each other). On a real interface (``eth0``, ``enp3s0`` …) the configuration is Unitree SDK2's:
that interface, default multicast discovery. With no interface, CycloneDDS picks one itself.

QoS: writers are CycloneDDS's default (reliable, keep last 1); readers are best effort and
keep only the newest sample, so a slow reader never works through a backlog of old states.
"""

from __future__ import annotations

from xml.sax.saxutils import quoteattr

from cyclonedds._clayer import ddspy_take
from cyclonedds.core import DDSException, InstanceState, SampleState, ViewState
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader, InvalidSample
from cyclonedds.topic import Topic

from agents.deploy.messages import TOPIC_LOWCMD, TOPIC_LOWSTATE, LowCmd_, LowState_

LOOPBACK_INTERFACES = ("lo", "lo0")
_ANY_SAMPLE = SampleState.Any | ViewState.Any | InstanceState.Any
MAX_LOCAL_PARTICIPANTS = 20


class TransportError(RuntimeError):
    """The DDS domain could not be set up (bad interface name, CycloneDDS error)."""


def cyclonedds_config(interface: str | None) -> str | None:
    """The CycloneDDS XML configuration for ``interface`` (None: CycloneDDS's own choice)."""
    if interface is None:
        return None
    nic = f"<NetworkInterface name={quoteattr(interface)} priority=\"default\" multicast=\"default\"/>"
    if interface in LOOPBACK_INTERFACES:
        general = f"<Interfaces>{nic}</Interfaces><AllowMulticast>false</AllowMulticast>"
        discovery = ("<ParticipantIndex>auto</ParticipantIndex>"
                     f"<MaxAutoParticipantIndex>{MAX_LOCAL_PARTICIPANTS}</MaxAutoParticipantIndex>"
                     "<Peers><Peer address=\"127.0.0.1\"/></Peers>")
    else:
        general, discovery = f"<Interfaces>{nic}</Interfaces>", ""
    return (f"<CycloneDDS><Domain Id=\"any\"><General>{general}</General>"
            f"<Discovery>{discovery}</Discovery></Domain></CycloneDDS>")


class G1Domain:
    """A participant on ``domain_id`` over ``interface`` with the two G1 topics."""

    def __init__(self, domain_id: int = 0, interface: str | None = None):
        try:
            self._domain = Domain(domain_id, cyclonedds_config(interface))
            self.participant = DomainParticipant(domain_id)
            self.lowstate_topic = Topic(self.participant, TOPIC_LOWSTATE, LowState_)
            self.lowcmd_topic = Topic(self.participant, TOPIC_LOWCMD, LowCmd_)
        except DDSException as exc:
            raise TransportError(f"CycloneDDS domain {domain_id} on interface {interface or '(auto)'}: {exc}. "
                                 "Check the interface name (ip link) and that no other domain with a different "
                                 "configuration is open in this process.") from exc
        self.domain_id, self.interface = domain_id, interface

    def mocap_topic(self, name: str) -> Topic:
        """A motion-capture topic (``agents.deploy.mocap.MocapFrame_``)."""
        from agents.deploy.mocap import MocapFrame_

        try:
            return Topic(self.participant, name, MocapFrame_)
        except DDSException as exc:
            raise TransportError(f"mocap topic {name!r}: {exc}") from exc

    def writer(self, topic: Topic) -> DataWriter:
        return DataWriter(self.participant, topic)

    def latest_reader(self, topic: Topic) -> DataReader:
        qos = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(1))
        return DataReader(self.participant, topic, qos=qos)


def take_latest_bytes(reader: DataReader) -> bytes | None:
    """``take_latest`` without decoding: the newest unread sample's serialized bytes (CDR with
    its encapsulation header), or None. The runner reads the LowState from these bytes itself
    (``messages.robot_state_from_cdr``); CycloneDDS's ``take`` would build the message object
    first. Uses the C layer's take, as ``DataReader.take`` does."""
    ret = ddspy_take(reader._ref, _ANY_SAMPLE, 4)
    if isinstance(ret, int):
        raise DDSException(ret, f"Occurred while taking data in {reader!r}")
    samples = [data for data, info in ret if info.valid_data]
    return samples[-1] if samples else None


def take_latest(reader: DataReader):
    """The newest unread sample, or None (one call, never blocks). Instance-state notices
    (e.g. the writer went away) carry no data and are skipped."""
    samples = [s for s in reader.take(N=4) if not isinstance(s, InvalidSample)]
    return samples[-1] if samples else None
