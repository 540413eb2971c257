"""Messages a person reads: lists of names, an object's size."""

from pipeline.messages import LIST_LIMIT, names_or_count, size_in_words


def test_a_few_names_are_listed_more_are_counted():
    few = [f"IMG_{i}" for i in range(LIST_LIMIT)]
    assert names_or_count(few) == ", ".join(few)
    many = [f"IMG_{i}" for i in range(48)]
    text = names_or_count(many, "of the 59 photos", look="ws/masks/overlays")
    assert text == "48 of the 59 photos (IMG_0, IMG_1, IMG_2, …; see ws/masks/overlays)"
    assert "IMG_47" not in names_or_count(many)


def test_a_size_in_millimetres_only_with_a_known_scale():
    size = {"height": 0.25, "width": 0.1204, "depth": 0.0996}
    assert size_in_words(size, True) == "250 × 120 × 100 mm (height × width × depth, from the printed board)"
    assert size_in_words(size, False).startswith("the scale is arbitrary (no printed board was seen")
