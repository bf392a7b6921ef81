"""The shipped Fast DDS profile for large images and its measurement tool."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import pytest
from conftest import ros_domain

from rsvo_ros.ros.dds import (
    DEFAULT_SHM_SEGMENT_BYTES,
    LARGE_IMAGES_PROFILE,
    PROFILE_ENV,
    main,
    measure,
    profile_env,
    table,
)

NS = {"p": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}


def test_the_profile_keeps_the_default_transports_with_a_larger_segment():
    root = ET.parse(LARGE_IMAGES_PROFILE).getroot()
    transports = {t.find("p:transport_id", NS).text: t for t in
                  root.iterfind("p:transport_descriptors/p:transport_descriptor", NS)}
    kinds = {tid: t.find("p:type", NS).text for tid, t in transports.items()}
    assert sorted(kinds.values()) == ["SHM", "UDPv4"]  # Fast DDS's defaults, nothing else
    shm = next(t for tid, t in transports.items() if kinds[tid] == "SHM")
    segment = int(shm.find("p:segment_size", NS).text)
    assert segment > 1280 * 720 * 3 > DEFAULT_SHM_SEGMENT_BYTES  # 720p colour fits
    participant = root.find("p:participant", NS)
    assert participant.get("is_default_profile") == "true"
    used = [t.text for t in participant.iterfind("p:rtps/p:userTransports/p:transport_id", NS)]
    assert sorted(used) == sorted(transports)
    assert participant.find("p:rtps/p:useBuiltinTransports", NS).text == "false"


def test_profile_env_sets_or_removes_the_profile_file(monkeypatch):
    monkeypatch.setenv(PROFILE_ENV, "/somewhere/else.xml")
    assert PROFILE_ENV not in profile_env("default")
    assert profile_env("large_images")[PROFILE_ENV] == str(LARGE_IMAGES_PROFILE)
    with pytest.raises(ValueError, match="'default' or 'large_images'"):
        profile_env("fast")


def test_without_arguments_it_prints_the_profile_path(capsys):
    assert main([]) == 0
    assert capsys.readouterr().out.strip() == str(LARGE_IMAGES_PROFILE)
    for bad in ("1280-720", "0x480", "640x-1"):  # the tools' parser (rsvo_synth's)
        with pytest.raises(SystemExit):
            main(["--measure", "--resolution", "1280x720", bad])
        assert "WIDTHxHEIGHT in positive whole numbers" in capsys.readouterr().err


def test_table_rows():
    rows = [{"resolution": "1280x720", "encoding": "mono8", "image_bytes": 921600,
             "profile": "default", "sent": 10, "received": 10, "transport_ms_median": 14.04,
             "transport_ms_p95": 16.0},
            {"resolution": "1280x720", "encoding": "mono8", "image_bytes": 921600,
             "profile": "large_images", "sent": 10, "received": 0,
             "transport_ms_median": None, "transport_ms_p95": None}]  # fmt: skip
    lines = table(rows).splitlines()
    assert lines[2] == "| 1280x720 mono8 | 900 KB | default | 10 / 10 | 14.0 / 16.0 ms |"
    assert lines[3].endswith("| large_images | 0 / 10 | - |")


@pytest.mark.ros
def test_large_images_cross_processes_with_the_profile(monkeypatch):
    """A publisher and a subscriber process that load the profile exchange every 1280x720
    image (a profile Fast DDS rejected, or transports that do not match, would lose them)."""
    monkeypatch.setenv("ROS_DOMAIN_ID", str(ros_domain(5)))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    row = measure(1280, 720, "mono8", "large_images", frames=8, rate=10.0)
    assert row["received"] == 8, row
    assert row["transport_ms_median"] > 0.0
