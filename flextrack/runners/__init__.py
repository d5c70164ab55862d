"""Shells around the tracker core: virtual-time replay, real-time live runs, the demo and `flextrack track`."""
