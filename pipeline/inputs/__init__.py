"""Reading the user's inputs: photos as phones and cameras write them, and a video's frames."""
