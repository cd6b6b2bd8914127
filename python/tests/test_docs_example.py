"""docs/python.md's example (numpy simulation -> Accumulator -> estimate -> pupil), run
exactly as written there."""
import os
import re

from conftest import ROOT


def test_docs_example(capsys):
    text = open(os.path.join(ROOT, "docs", "python.md")).read()
    code = re.search(r"<!-- example:start -->\s*```python\n(.*?)```\s*<!-- example:end -->", text, re.S).group(1)
    ns = {}
    exec(compile(code, "docs/python.md example", "exec"), ns)
    out = capsys.readouterr().out
    assert "recovered to" in out
    # The numbers it prints: a 27 nm NCP (piston, tip, tilt removed) found to ~4 nm.
    assert 20e-9 < ns["ncp_rms_ptt"] < 35e-9
    assert ns["err"] < 0.25 * ns["ncp_rms_ptt"], (ns["err"], ns["ncp_rms_ptt"])
    assert ns["halo"].valid_fraction > 0.9
