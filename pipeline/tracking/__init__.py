"""Streaming tie points of image flights: the tracker and its ``tracking:`` options."""
