"""`sim.seeding.parse_seeds`: the seed lists `sudd datagen --seeds` takes."""

import pytest

from sim.seeding import parse_seeds


def test_items_and_inclusive_ranges_keep_their_order_without_repeats():
    assert parse_seeds("100015,100003,7-9, 8 3") == (100015, 100003, 7, 8, 9, 3)


def test_a_file_of_seeds_with_comments(tmp_path):
    f = tmp_path / "failures.txt"
    f.write_text("# drawer_open failures of step 28\n100003  # never held the handle\n100015\n700000-700002,5\n")
    assert parse_seeds(str(f)) == (100003, 100015, 700000, 700001, 700002, 5)


@pytest.mark.parametrize("spec, names", [("12,x7", "'x7'"), ("9-3", "'9-3'"), ("1.5", "'1.5'"), ("", "names no"),
                                         ("-4", "'-4'")])
def test_bad_lists_name_the_item(spec, names):
    with pytest.raises(ValueError, match="seeds") as e:
        parse_seeds(spec)
    assert names in str(e.value)
