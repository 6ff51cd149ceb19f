"""Views of a target's static links: the links an item was mapped with, kept so that fusing it again (a rewind on
arrival, :mod:`.arrival`) maps it the same way.

Why: ordered processing maps an item into ``base`` with the links in use when it leaves the synchronizer. Fusion
on arrival fuses earlier and again later; it remembers per item the links it was resolved with (a view: a shallow
copy of every chain's :class:`~.frame_chain.StaticLinks`, whose link arrays are replaced, never changed in place)
and maps it with those. The chains map with their ``links`` attribute, so :meth:`LinkViews.apply` puts a view
there for the one item and the caller puts the previous links back (``try`` / ``finally``); the chain's other
state (live rig and base poses) is its own.
"""

from __future__ import annotations

import copy

from fullperc_fusion.pipeline.frame_chain import FrameChain, StaticLinks

View = tuple[StaticLinks, ...]   # one per chain: the primary chain's, then each further local source's


def _copy_links(links: StaticLinks) -> StaticLinks:
    v = copy.copy(links)
    v.estimates = dict(links.estimates)
    v.sources = dict(links.sources)
    return v


def _signature(links: StaticLinks) -> tuple:
    return id(links.T_omc_base), id(links.T_base_ots), id(links.T_rig_ots), links.generation


class LinkViews:
    """The chains of one target and the view of their links in use now (:attr:`current`)."""

    __slots__ = ("_sig", "chains", "current")

    def __init__(self, chains: list[FrameChain]) -> None:
        self.chains = chains
        self._sig = self._signatures()
        self.current: View = self._view()

    def _signatures(self) -> tuple:
        return tuple(_signature(ch.links) for ch in self.chains)

    def _view(self) -> View:
        return tuple(_copy_links(ch.links) for ch in self.chains)

    def refresh(self) -> bool:
        """Take a new :attr:`current` view if a chain's links changed since the last one; True if they did."""
        sig = self._signatures()
        if sig == self._sig:
            return False
        self._sig = sig
        self.current = self._view()
        return True

    def apply(self, view: View) -> View:
        """Map with ``view`` from now on; returns the links that were in use (for :meth:`apply` back)."""
        was = tuple(ch.links for ch in self.chains)
        for ch, links in zip(self.chains, view, strict=True):
            ch.links = links
        return was
