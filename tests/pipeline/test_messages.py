"""Lists of names in messages."""

from pipeline.messages import LIST_LIMIT, names_or_count


def test_a_few_names_are_listed_more_are_counted():
    few = [f"IMG_{i}" for i in range(LIST_LIMIT)]
    assert names_or_count(few) == ", ".join(few)
    many = [f"IMG_{i}" for i in range(48)]
    text = names_or_count(many, "of the 59 photos", look="ws/masks/overlays")
    assert text == "48 of the 59 photos (IMG_0, IMG_1, IMG_2, …; see ws/masks/overlays)"
    assert "IMG_47" not in names_or_count(many)
