"""mathops.take_rows: the index_select form of a gather gives advanced indexing's values."""

from __future__ import annotations

import pytest
import torch

from torchvol.ops.mathops import take_rows


@pytest.mark.parametrize("table_shape", [(512,), (256, 3), (7, 2, 2)])
@pytest.mark.parametrize("index_shape", [(0,), (1,), (1000,), (250, 8)])
@pytest.mark.parametrize("index_dtype", [torch.int64, torch.int32])
def test_take_rows_is_advanced_indexing(table_shape, index_shape, index_dtype):
    g = torch.Generator().manual_seed(0)
    table = torch.randn(table_shape, generator=g)
    index = torch.randint(0, table_shape[0], index_shape, generator=g).to(index_dtype)
    got, want = take_rows(table, index), table[index.long()]
    assert got.shape == want.shape and torch.equal(got, want), (got.shape, want.shape)
