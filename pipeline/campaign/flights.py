"""The flights of a campaign: flight folders given one by one, or campaign folders holding
them (docs/formats.md, *Campaigns*)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from pipeline.common.paths import exists_as_anything, file_problem
from seqat.errors import InputDataError

FLIGHT_YAML = "flight.yaml"


@dataclass(frozen=True, kw_only=True)
class CampaignFlight:
    """One flight: its folder and its name (the folder's name: its run folder ``OUT/<name>``)."""

    name: str
    folder: Path


def is_campaign_folder(path: Path) -> bool:
    """A folder without ``flight.yaml`` holding at least one flight folder."""
    return (path.is_dir() and not (path / FLIGHT_YAML).exists()
            and any((sub / FLIGHT_YAML).is_file() for sub in path.iterdir() if sub.is_dir()))


def find_flights(paths: Sequence[Path]) -> tuple[CampaignFlight, ...]:
    """The flights, in the order given (a campaign folder's flights by name).

    Raises
    ------
    InputDataError
        A path that is neither a flight folder nor a campaign folder, or two flights of one
        name (their run folders would collide).
    """
    flights: list[CampaignFlight] = []
    for path in paths:
        if (path / FLIGHT_YAML).is_file():
            flights.append(CampaignFlight(name=path.resolve().name, folder=path))
        elif is_campaign_folder(path):
            flights.extend(CampaignFlight(name=sub.name, folder=sub)
                           for sub in sorted(path.iterdir())
                           if sub.is_dir() and (sub / FLIGHT_YAML).is_file())
        elif not path.is_dir():
            raise InputDataError(f"{path}: {file_problem(path)}" if exists_as_anything(path)
                                 else f"{path}: no such flight folder")
        else:
            raise InputDataError(f"{path}: not a flight folder (no {FLIGHT_YAML}) nor a "
                                 f"campaign folder (no subfolder with {FLIGHT_YAML})")
    seen: dict[str, Path] = {}
    for flight in flights:
        if flight.name in seen:
            raise InputDataError(f"{flight.folder}: a second flight named {flight.name!r} "
                                 f"(first: {seen[flight.name]}); its run folder would be the "
                                 "same: rename one folder")
        seen[flight.name] = flight.folder
    return tuple(flights)
