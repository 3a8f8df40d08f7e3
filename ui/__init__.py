"""The Gradio studio: layout (`layout`) and event handlers (`studio`); no tensor maths here."""
