"""The notebooks run top to bottom with their small parameters (a cell that raises fails the suite)."""

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


def test_the_four_notebooks_of_the_design_are_there():
    names = [p.stem for p in NOTEBOOKS]
    assert names == ["01_world", "02_train_su", "03_multi_user", "04_evaluate"]
    for path in NOTEBOOKS:
        book = nbformat.read(path, as_version=4)
        tagged = [c for c in book.cells if "parameters" in c.metadata.get("tags", [])]
        assert len(tagged) == 1, f"{path.name}: one cell tagged 'parameters'"
        assert "real run" in tagged[0].source, f"{path.name}: the parameters cell notes the real budget"
        assert all(not c.get("outputs") for c in book.cells if c.cell_type == "code"), (
            "commit without outputs"
        )


# Training one (02), the multi-user episodes (03) and evaluating through every engine (04) take 1-3
# minutes each on a 2-core developer machine; their code paths run in the default suite elsewhere
# (test_run_cli, test_evaluation, test_pretrained), so only the slow set runs them as notebooks.
HEAVY = {"02_train_su", "03_multi_user", "04_evaluate"}


@pytest.mark.parametrize(
    "path",
    [pytest.param(p, id=p.stem, marks=[pytest.mark.slow] if p.stem in HEAVY else []) for p in NOTEBOOKS],
)
def test_notebook_runs(path, tmp_path):
    book = nbformat.read(path, as_version=4)
    # the kernel writes its GIFs and evaluation folders into tmp_path, not into notebooks/
    NotebookClient(
        book, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    ).execute()
    errors = [o for c in book.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"]
    assert not errors
    images = [
        o for c in book.cells if c.cell_type == "code" for o in c.outputs if "image/png" in o.get("data", {})
    ]
    assert images, f"{path.name} drew no picture"
