"""Building the OPC 40100 instance cheaply on asyncua's server.

asyncua instantiates an object type with all its optional children; vgripd then removes the
ones it does not implement (``opcua_vision.NOT_IMPLEMENTED``). asyncua's own ``delete_nodes``
with ``DeleteTargetReferences`` looks for references to each deleted node in every node of the
address space (about 25 000 references once the NodeSet is in), once per node: about 1.5 s of
CPU for the 24 subtrees at every start of the link. ``prune`` removes the same nodes and the same
references and nothing else: the only references into a freshly instantiated subtree are the
hierarchical one from its parent (deleted first, both directions) and those among its own nodes
(deleted with them). ``references_to_missing`` finds any reference left to a node that is not
there (the tests check the address space has none).
"""

from __future__ import annotations

from collections.abc import Iterable

from asyncua import Node, Server, ua
from asyncua.common.manage_nodes import delete_nodes


async def prune(server: Server, roots: Iterable[Node]) -> None:
    """Remove each node of ``roots`` with everything below it (hierarchical references)."""
    session = server.iserver.isession
    for root in roots:
        parents = await root.get_references(refs=ua.ObjectIds.HierarchicalReferences,
                                            direction=ua.BrowseDirection.Inverse)
        for ref in parents:
            await server.get_node(ref.NodeId).delete_reference(
                root.nodeid, ref.ReferenceTypeId, forward=True, bidirectional=True)
        await delete_nodes(session, [root], recursive=True, delete_target_references=False)


def references_to_missing(server: Server) -> list[tuple[ua.NodeId, ua.NodeId]]:
    """(source, target) of every reference whose target is not in the address space."""
    aspace = server.iserver.aspace
    return [(source, ref.NodeId) for source in list(aspace.keys())
            for ref in aspace[source].references if ref.NodeId not in aspace]
