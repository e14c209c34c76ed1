"""The project's licence file (issue 36, finding 10): pyproject.toml declares Apache-2.0, LICENSE holds its text."""

import re

from conftest import REPO


def test_license_file_is_the_apache_2_text():
    text = (REPO / "LICENSE").read_text()
    assert "Apache License" in text and "Version 2.0, January 2004" in text
    sections = re.findall(r"^\s+(\d)\. ([A-Z][^.]+)\.", text, flags=re.M)
    assert [n for n, _ in sections] == [str(i) for i in range(1, 10)]
    assert "END OF TERMS AND CONDITIONS" in text
    assert 'license = "Apache-2.0"' in (REPO / "pyproject.toml").read_text()
