"""`sim.seeding.parse_seeds`: the seed lists `sudd datagen --seeds` takes."""

import pytest

from sim.seeding import parse_seeds, resolve_seeds


def test_items_and_inclusive_ranges_keep_their_order_without_repeats():
    assert parse_seeds("100015,100003,7-9, 8 3") == (100015, 100003, 7, 8, 9, 3)


def test_a_file_of_seeds_with_comments(tmp_path):
    f = tmp_path / "failures.txt"
    f.write_text("# drawer_open failures of step 28\n100003  # never held the handle\n100015\n700000-700002,5\n")
    assert parse_seeds(str(f)) == (100003, 100015, 700000, 700001, 700002, 5)


def test_a_list_too_long_for_a_file_name_is_read_as_a_list():
    seeds = list(range(100500, 100700, 2))  # 700 characters: os.stat of it as a path raised "File name too long"
    assert parse_seeds(",".join(map(str, seeds))) == tuple(seeds)
    with pytest.raises(ValueError, match="is not a seed"):
        parse_seeds("x" * 600)


@pytest.mark.parametrize("spec, names", [("12,x7", "'x7'"), ("9-3", "'9-3'"), ("1.5", "'1.5'"), ("", "names no"),
                                         ("-4", "'-4'")])
def test_bad_lists_name_the_item(spec, names):
    with pytest.raises(ValueError, match="seeds") as e:
        parse_seeds(spec)
    assert names in str(e.value)


def test_a_command_line_names_a_count_from_an_offset_or_a_list():
    assert resolve_seeds(None, 3, None, default_episodes=20, default_offset=100) == (100, 101, 102)
    assert resolve_seeds(None, None, 7, default_episodes=2, default_offset=100) == (7, 8)
    assert resolve_seeds("5,2", None, None, default_episodes=None, default_offset=0) == (5, 2)
    with pytest.raises(ValueError, match="at least 1"):
        resolve_seeds(None, 0, None, default_episodes=20, default_offset=0)
