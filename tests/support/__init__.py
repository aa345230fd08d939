"""What several test packages share: databases built once by the migrations and copied."""
