"""The project must not depend on files outside itself at run time."""

from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def test_no_runtime_reference_to_the_shared_folder():
    offenders = []
    for folder in ("acoustlab", "plugins", "conf"):
        for path in (REPO / folder).rglob("*"):
            if path.suffix in {".py", ".yaml", ".yml", ".csv"} and "../shared" in path.read_text(errors="ignore"):
                offenders.append(str(path.relative_to(REPO)))
    assert not offenders, offenders


def test_shipped_audio_has_attribution():
    notice = (REPO / "NOTICE.md").read_text()
    for audio in (REPO / "acoustlab" / "data").rglob("*.flac"):
        assert audio.name in notice, f"{audio.name} has no attribution in NOTICE.md"
